"""Per-part signed distances and the energy terms: known depths, known values and gradients."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from retarget_core import rotations as rot
from retarget_core.body_parts import body_parts
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.energy.mesh_distance import (
    MeshDistance,
    cap_boundary_loops,
    closest_point_distance,
    signed_distance_grid,
)
from retarget_core.energy.sdf import (
    _sample_grid,
    build_part_sdf,
    distance_matrix,
    effective_depth,
    sample_pairs,
    segment_matrices,
    vertex_depths,
)
from retarget_core.energy.terms import (
    end_effector_energy,
    foot_energy,
    interpenetration_energy,
    root_velocity_energy,
    rotation_energy,
    total_energy,
    vertex_contact_energy,
    weak_energy,
)
from retarget_core.energy.weights import EnergyConfig, EnergyWeights, load_energy_config

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest_contacts import SMALL, box_pose, two_boxes  # noqa: E402


@pytest.fixture(scope="module")
def boxes():
    ch, mapping = two_boxes()
    parts = body_parts(ch, mapping)
    return ch, mapping, parts, build_part_sdf(ch, parts)


def _pose(ch, parts, depth, dtype=torch.float32):  # type: ignore[no-untyped-def]
    grot, gpos = box_pose(depth, dtype=dtype)
    return ch.pose_vertices(grot, gpos), segment_matrices(ch, parts, grot, gpos)


# --- mesh distance building blocks -------------------------------------------------------------------------


def test_closest_point_distance_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(200, 3, 3))
    p = rng.normal(size=(200, 3)) * 2
    d = closest_point_distance(p, tri[:, 0], tri[:, 1], tri[:, 2])
    # Dense barycentric sampling of each triangle gives an upper bound converging to the distance.
    u, v = np.meshgrid(np.linspace(0, 1, 120), np.linspace(0, 1, 120))
    keep = (u + v) <= 1
    u, v = u[keep], v[keep]
    pts = tri[:, None, 0] + u[None, :, None] * (tri[:, None, 1] - tri[:, None, 0]) + v[None, :, None] * (tri[:, None, 2] - tri[:, None, 0])
    brute = np.linalg.norm(pts - p[:, None], axis=-1).min(1)
    assert np.all(d <= brute + 1e-9)
    assert np.max(brute - d) < 0.03


def test_signed_distance_grid_of_a_sphere() -> None:
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    md = MeshDistance(np.asarray(m.vertices), np.asarray(m.faces), spacing=0.05)
    origin, voxel, shape = np.array([-0.6, -0.6, -0.6]), 0.04, (31, 31, 31)
    sd = signed_distance_grid(origin, voxel, shape, md)
    g = np.stack(np.meshgrid(*[origin[a] + np.arange(shape[a]) * voxel for a in range(3)], indexing="ij"), -1)
    exact = np.linalg.norm(g, axis=-1) - 0.5
    # The icosphere's facets are within 3 mm of the sphere; voxels are 4 cm. Within the exact band (3 voxels)
    # the error is the facets'; beyond it closest-point propagation stays within 0.4 voxel.
    band = np.abs(exact) < 3 * voxel
    assert np.abs(sd - exact)[band].max() < 0.005
    assert np.abs(sd - exact)[~band].max() < 0.4 * voxel
    assert np.all(((sd < 0) == (exact < 0)) | (np.abs(exact) < 0.004))


def test_cap_boundary_loops_closes_a_cut_part() -> None:
    box = trimesh.creation.box(extents=(1, 1, 1))
    keep = box.triangles_center[:, 2] < 0.4  # drop the top face: one square hole
    v, f = cap_boundary_loops(np.asarray(box.vertices), np.asarray(box.faces)[keep])
    closed = trimesh.Trimesh(v, f, process=False)
    assert closed.is_watertight
    assert closed.volume == pytest.approx(1.0)


# --- per-part SDF: boxes pushed into each other by a known depth -------------------------------------------


@pytest.mark.parametrize("depth", [0.004, 0.01, 0.03, 0.06])
def test_box_penetration_depth_is_measured(boxes, depth: float) -> None:
    ch, _, parts, sdf = boxes
    verts, mats = _pose(ch, parts, depth)
    samples = sample_pairs(sdf, verts, mats)
    measured = float(vertex_depths(sdf, samples, 1).max())
    assert measured == pytest.approx(depth, abs=1e-3)
    # The small box's bottom face is `depth` inside the big one; paper 2's M_dist says the same.
    dist = distance_matrix(sdf, samples, 1)[0]
    hand, hips = parts.index("LeftHand"), parts.index("Hips")
    assert float(dist[hand, hips]) == pytest.approx(-depth, abs=1e-3)
    # Big-box vertices inside the small box: only its top-centre vertex, at depth min(depth, SMALL - depth)
    # from the small box's bottom and top faces, or SMALL / 2 from its sides.
    assert float(dist[hips, hand]) == pytest.approx(-min(depth, SMALL - depth, SMALL / 2), abs=1e-3)


@pytest.mark.parametrize("depth", [-0.005, 0.01, 0.03])
def test_pair_samples_of_a_vertex_subset_inside_only(boxes, depth: float) -> None:
    """Posing only the hand box's vertices (the parts with an allowed pair) and sampling inside points only
    finds the same penetrating samples, at the same distances, as sampling the whole mesh."""
    ch, _, parts, sdf = boxes
    verts, mats = _pose(ch, parts, depth)
    hand = parts.index("LeftHand")
    allowed = sdf.allowed.clone()
    allowed[torch.arange(parts.num_parts) != hand] = False
    full = sample_pairs(sdf, verts, mats, allowed)
    subset = torch.nonzero(parts.vertex_part == hand).flatten()
    part = sample_pairs(sdf, verts[:, subset], mats, allowed, vertices=subset, inside_only=True)

    def inside(s):  # type: ignore[no-untyped-def]
        keep = s.distance < 0
        return sorted(zip(s.vertex[keep].tolist(), s.part[keep].tolist(), s.distance[keep].tolist(), strict=True))

    assert inside(part) == inside(full)
    assert (len(inside(full)) > 0) == (depth > 0)
    assert len(part.frame) <= len(full.frame)


def test_boxes_apart_do_not_penetrate(boxes) -> None:
    ch, _, parts, sdf = boxes
    verts, mats = _pose(ch, parts, -0.005)  # a 5 mm gap
    samples = sample_pairs(sdf, verts, mats)
    assert float(vertex_depths(sdf, samples, 1).max()) == 0.0
    d = distance_matrix(sdf, samples, 1)[0]
    assert float(d[parts.index("LeftHand"), parts.index("Hips")]) == pytest.approx(0.005, abs=1e-3)
    assert float(interpenetration_energy(sdf, verts, mats)[0]) == 0.0
    assert float(sdf.rest_depth.max()) == 0.0  # nothing touches in the bind pose


def test_interpenetration_energy_grows_with_depth_and_has_gradients(boxes) -> None:
    ch, _, parts, sdf = boxes
    values = []
    for depth in (0.005, 0.01, 0.02):
        verts, mats = _pose(ch, parts, depth)
        values.append(float(interpenetration_energy(sdf, verts, mats)[0]))
    assert 0 < values[0] < values[1] < values[2]
    # Known value: the small box's bottom-face vertices are 2 cm deep, the big box's top-centre vertex too;
    # E = sum of (vertex area / 1 cm^2) * depth^2, at 1.80 m scale.
    s = sdf.scale_to_180
    verts, _ = _pose(ch, parts, 0.02)
    hand_v = parts.part_vertices(parts.index("LeftHand"))
    bottom = hand_v[verts[0, hand_v, 1] < verts[0, hand_v, 1].min() + 1e-6]
    centre = torch.nonzero((ch.vertices - torch.tensor([0.0, 0.4, 0.0])).norm(dim=1) < 1e-6).flatten()
    area = float(sdf.vertex_area[bottom].sum() + sdf.vertex_area[centre].sum())
    assert values[2] == pytest.approx(area * s**2 / 1e-4 * (0.02 * s) ** 2, rel=1e-3)

    ch64, _ = two_boxes(torch.float64)

    def energy(depth: torch.Tensor) -> torch.Tensor:
        verts, mats = _pose(ch64, parts, depth, dtype=torch.float64)
        return interpenetration_energy(sdf, verts, mats).sum()

    d0 = torch.tensor(0.013, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(energy(d0), d0)
    eps = 1e-5
    numeric = (energy(d0.detach() + eps) - energy(d0.detach() - eps)) / (2 * eps)
    assert float(grad) > 0
    assert float(grad) == pytest.approx(float(numeric), rel=1e-3)


def test_rest_depth_is_subtracted(boxes) -> None:
    """A vertex already inside a part in the bind pose only counts the depth beyond that."""
    ch, _, parts, sdf = boxes
    verts, mats = _pose(ch, parts, 0.02)
    samples = sample_pairs(sdf, verts, mats)
    into_hips = samples.part == parts.index("Hips")
    base = effective_depth(sdf, samples)[into_hips].max()
    sdf.rest_depth[:, parts.index("Hips")] += 0.005
    try:
        assert float(effective_depth(sdf, samples)[into_hips].max()) == pytest.approx(float(base) - 0.005, abs=1e-6)
    finally:
        sdf.rest_depth[:, parts.index("Hips")] -= 0.005


# --- the other terms -----------------------------------------------------------------------------------------


def test_vertex_contact_energy() -> None:
    posed = torch.zeros(3, 4, 3, requires_grad=True)
    with torch.no_grad():
        posed[1, 2] = torch.tensor([0.03, 0.0, 0.04])  # 5 cm from vertex 0
    c = ContactConstraints(3, torch.tensor([1, 1]), torch.tensor([0, 1]), torch.tensor([2, 3]), torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long), [])
    e = vertex_contact_energy(posed, c, height=0.9)  # a 0.9 m body: distances double at 1.80 m
    assert e.shape == (3,)
    assert float(e[1].detach()) == pytest.approx((0.05 * 2) ** 2 / 2)
    assert float(e[0].detach()) == 0.0 and float(e[2].detach()) == 0.0
    e.sum().backward()
    assert posed.grad is not None and posed.grad[1, 2].abs().sum() > 0


def test_foot_energy_planted_then_sliding() -> None:
    f = 6
    g = torch.zeros(f, 2, 3)
    g[:, 0, 1] = 0.05  # joint 0 at its rest height
    g[3:, 0, 0] = torch.arange(3) * 0.02  # then slides 2 cm per frame
    labels = torch.zeros(f, 4, dtype=torch.bool)
    labels[:, 1] = True  # column 1 (left heel) is joint 0
    feet = FootContacts(labels, [-1, 0, -1, -1])
    rest = torch.tensor([[0.0, 0.05, 0.0], [0.0, 0.0, 0.0]])
    g.requires_grad_(True)
    e = foot_energy(g, rest, feet, height=2.0)
    assert torch.allclose(e[:4], torch.zeros(4))
    assert float(e[4].detach()) == pytest.approx(0.02**2 / 2.0)
    e.sum().backward()
    # d/dx of the last frame's term only (earlier frames' velocity terms cancel between neighbours).
    assert g.grad is not None and float(g.grad[5, 0, 0]) == pytest.approx(2 * 0.02 / 2.0)


def test_weak_and_end_effector_energies() -> None:
    theta = math.radians(40)
    qa = rot.identity(2, 3)
    qb = qa.clone()
    qb[:, 1] = torch.tensor([0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)])  # 40 degrees about z
    assert torch.allclose(rotation_energy(qb, qa), torch.full((2,), 4 * (1 - math.cos(theta))), atol=1e-5)
    assert torch.allclose(rotation_energy(qa, qa), torch.zeros(2))
    root_a = torch.tensor([[0.0, 0, 0], [0.1, 0, 0]])
    root_b = torch.tensor([[0.0, 0, 0], [0.2, 0, 0]])
    assert torch.allclose(root_velocity_energy(root_b, root_a, leg_ratio=2.0), torch.zeros(2))
    assert float(root_velocity_energy(root_b, root_a, 1.0)[1]) == pytest.approx(0.01)
    w = weak_energy(qb, qa, root_b, root_a, 1.0, rho=10.0)
    assert float(w[1]) == pytest.approx(10 * 4 * (1 - math.cos(theta)) + 0.01, rel=1e-5)
    # End effectors: the same motion on bodies of different heights, scaled, costs nothing.
    pa = torch.cumsum(torch.rand(5, 4, 3), dim=0)
    assert torch.allclose(end_effector_energy(pa * 1.2, pa, 1.2, 1.0), torch.zeros(5), atol=1e-6)
    assert float(end_effector_energy(pa * 2.0, pa, 1.0, 1.0).sum()) > 0


def test_total_energy_uses_the_papers_weights() -> None:
    w = EnergyWeights()
    assert (w.contact, w.interpenetration, w.foot, w.rotation, w.end_effector) == (1000, 100, 0.1, 1000, 1000)
    eso = EnergyConfig().eso
    assert (eso.weights.rotation, eso.weights.interpenetration, eso.weights.contact) == (10, 1, 100)
    assert eso.iterations == 30 and eso.learning_rate == 0.01 and eso.contact_gate_m == 0.15
    terms = {"contact": torch.tensor([1.0, 0.0]), "foot": torch.tensor([0.0, 2.0])}
    assert torch.allclose(total_energy(terms, w), torch.tensor([1000.0, 0.2]))
    with pytest.raises(ValueError):
        total_energy({}, w)


def test_energy_config_from_json(tmp_path: Path) -> None:
    path = tmp_path / "energy.json"
    path.write_text('{"eso": {"iterations": 5, "weights": {"contact": 7}}}')
    cfg = load_energy_config(path)
    assert cfg.eso.iterations == 5 and cfg.eso.weights.contact == 7
    assert cfg.eso.weights.foot == 0.1 and cfg.training.weights.contact == 1000
    assert load_energy_config() == EnergyConfig()


def test_part_sdf_of_a_real_body_is_consistent(shared_data: Path) -> None:
    """On a shared body: each part's own surface lies at distance ~0 of its field, and nothing penetrates in
    the bind pose beyond the thighs of the bulky body touching."""
    from retarget_core.loading import load_character

    loaded = load_character(shared_data / "characters" / "mh_male_bulky.glb")
    ch = loaded.character
    parts = body_parts(ch, loaded.mapping)
    sdf = build_part_sdf(ch, parts)
    eye = torch.eye(3, 4).expand(1, parts.num_parts, 3, 4)
    rest = ch.vertices[None]
    samples = sample_pairs(sdf, rest, eye)
    assert float(vertex_depths(sdf, samples, 1).max()) < 1e-6  # bind-pose depth is subtracted
    for name in ("LeftHand", "Spine1", "Head", "RightUpLeg"):
        s = parts.index(name)
        own = torch.unique(parts.faces[parts.face_part == s])
        d = _sample_grid(sdf, s, ch.vertices[own])
        assert float(d.abs().median()) < 0.002, name


def test_compiled_grid_lookup_matches_the_tensor_form_and_its_gradient() -> None:
    """The compiled lookup (:mod:`retarget_core.energy.sdf_kernel`) gives the tensor form's distances and
    gradients on points inside, near and outside a segment's grid (the blend band included)."""
    import torch.nn.functional as nnf

    from retarget_core.energy.sdf_kernel import sample_grid

    g = torch.Generator().manual_seed(3)
    grid = torch.randn(2, 6, 7, 8, generator=g, dtype=torch.float64) * 0.02  # values around the blend width
    lo, voxel, blend = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64), 0.01, 0.02
    hi = lo + voxel * torch.tensor([7.0, 6.0, 5.0], dtype=torch.float64)  # x, y, z: Nx - 1, Ny - 1, Nz - 1 voxels
    x = (lo - 0.02 + torch.rand(400, 3, generator=g, dtype=torch.float64) * (hi - lo + 0.04)).requires_grad_(True)

    def tensor_form(p: torch.Tensor) -> torch.Tensor:
        inside = torch.minimum(torch.maximum(p, lo), hi)
        norm = 2.0 * (inside - lo) / (hi - lo) - 1.0
        seg, char = nnf.grid_sample(grid[None], norm.view(1, 1, 1, -1, 3), align_corners=True).view(2, -1)
        q = (seg / blend).clamp(0.0, 1.0)
        return q * seg + (1.0 - q) * char + (p - inside).norm(dim=-1)

    want = tensor_form(x)
    got = sample_grid(grid, lo, voxel, blend, x)
    (g_want,) = torch.autograd.grad(want.sum(), x)
    (g_got,) = torch.autograd.grad(got.sum(), x)
    assert torch.allclose(got, want, atol=1e-12)
    assert torch.allclose(g_got, g_want, atol=1e-9)
    assert ((x < lo) | (x > hi)).any() and (g_want.abs() > 0.1).any()  # points outside; gradients not trivial


@pytest.mark.parametrize("inside_only", [False, True])
def test_compiled_pair_samples_match_the_tensor_search(boxes, shared_data: Path, monkeypatch, inside_only: bool) -> None:
    """Without gradients, :func:`sample_pairs` searches and samples through the compiled kernel
    (:mod:`retarget_core.energy.pair_samples_kernel`): the same samples in the same order, the same distances (to
    float64 rounding), as the tensor search it replaces, on boxes pushed into each other and on a real body."""
    import retarget_core.energy.sdf as sdf_module
    from retarget_core.loading import load_character

    ch, _, parts, sdf = boxes
    cases = [(sdf, *(x.double() for x in _pose(ch, parts, depth))) for depth in (-0.005, 0.01, 0.03)]
    loaded = load_character(shared_data / "characters" / "mh_male_bulky.glb")
    body_parts_ = body_parts(loaded.character, loaded.mapping)
    real = build_part_sdf(loaded.character, body_parts_)
    bent = loaded.character.vertices.double()[None].repeat(2, 1, 1)
    bent[1, :, 0] = bent[1, :, 0] * 0.9  # squeezed sideways: arms into the torso
    cases.append((real, bent, torch.eye(3, 4, dtype=torch.float64).expand(2, body_parts_.num_parts, 3, 4)))
    for s, verts, mats in cases:
        got = sample_pairs(s, verts, mats, inside_only=inside_only)
        with monkeypatch.context() as m:
            m.setattr(sdf_module, "_compiled_path", lambda *args: False)
            want = sample_pairs(s, verts, mats, inside_only=inside_only)
        assert len(want.frame) > 0
        for a, b in ((got.frame, want.frame), (got.vertex, want.vertex), (got.part, want.part)):
            assert torch.equal(a, b)
        assert torch.allclose(got.distance, want.distance, atol=1e-12, rtol=0)
