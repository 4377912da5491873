"""Contact detection (hands, feet), triangle intersection and vertex correspondence on constructed cases."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.bodies import load_preset
from retarget_core.body_parts import CLUSTERS, body_parts, mapping_by_name
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import build_correspondence, transfer_contacts
from retarget_core.contacts.foot_contact import FootContactParams, detect_foot_contacts, fill_window
from retarget_core.contacts.hand_distance import hand_part_distances
from retarget_core.contacts.self_contact import contact_mask, detect_self_contacts
from retarget_core.contacts.triangles import intersecting_pairs, triangles_intersect

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest_contacts import (  # noqa: E402
    BIG,
    SMALL,
    box_pose,
    cheek_vertex,
    hand_on_vertex_pose,
    hip_vertex,
    thigh_vertices,
    two_boxes,
)


@pytest.fixture(scope="module")
def average():
    c = load_preset("male_average")
    m = mapping_by_name(c.skeleton.names)
    return c, m, body_parts(c, m)


# --- triangle intersection ------------------------------------------------------------------------------


def test_triangles_intersect_known_cases() -> None:
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    through = np.array([[0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]])  # pierces the flat one
    above = through + np.array([0, 0, 1.0])
    beside = through + np.array([2.0, 0, 0])
    ta = np.stack([flat, flat, flat])
    tb = np.stack([through, above, beside])
    assert triangles_intersect(ta, tb).tolist() == [True, False, False]
    assert triangles_intersect(tb, ta).tolist() == [True, False, False]


def test_intersecting_pairs_match_brute_force() -> None:
    rng = np.random.default_rng(3)
    verts = np.repeat(rng.uniform(0, 1, (400, 3)), 3, axis=0) + rng.normal(0, 0.06, (1200, 3))
    fa = np.arange(600).reshape(-1, 3)
    fb = np.arange(600, 1200).reshape(-1, 3)
    got = {tuple(p) for p in intersecting_pairs(verts, fa, fb).tolist()}
    a, b = np.meshgrid(np.arange(200), np.arange(200), indexing="ij")
    hit = triangles_intersect(verts[fa[a.ravel()]], verts[fb[b.ravel()]])
    brute = set(zip(a.ravel()[hit].tolist(), b.ravel()[hit].tolist(), strict=True))
    assert got == brute and len(brute) > 5
    assert len(intersecting_pairs(verts, fa, fb, first_only=True)) >= 1


# --- hand self-contacts -----------------------------------------------------------------------------------


def _posed_clip(ch: Character, grot: torch.Tensor, gpos: torch.Tensor) -> torch.Tensor:
    return ch.pose_vertices(grot, gpos)


def _box_at(ch: Character, hand_centres: torch.Tensor) -> torch.Tensor:
    """The two-box body posed with the small box's centre at ``hand_centres (F, 3)`` (no rotation)."""
    grot, gpos = box_pose(0.0, len(hand_centres), dtype=ch.vertices.dtype)
    gpos[:, 2] = hand_centres.to(ch.vertices.dtype)
    return ch.pose_vertices(grot, gpos)


def _hand_on_top(gaps_180: list[float], ch: Character) -> torch.Tensor:
    """Small box centred above the big one, its bottom ``gap`` above the top face (gaps at 1.80 m, scaled to
    the two-box body; negative: sunk in)."""
    s = ch.height / 1.80
    y = torch.tensor([BIG + SMALL / 2 + g * s for g in gaps_180], dtype=ch.vertices.dtype)
    return _box_at(ch, torch.stack([torch.zeros_like(y), y, torch.zeros_like(y)], dim=1))


def test_hand_part_distance_is_exact_on_boxes() -> None:
    ch, mapping = two_boxes(torch.float64)
    parts = body_parts(ch, mapping)
    torso, own_arm = CLUSTERS.index("torso"), CLUSTERS.index("left_arm")
    # Face to face above the top, sunk in a little, fully inside, and corner to edge beside the top.
    s = ch.height / 1.80
    gaps = [0.002, 0.01, 0.04, -0.01, -0.36]  # at 1.80 m; -0.36 buries the 10 cm box 1 cm under the top
    posed = _hand_on_top(gaps, ch)
    dx, dy = 0.012, 0.009
    beside = torch.tensor([[BIG / 2 + dx + SMALL / 2, BIG + dy + SMALL / 2, 0.0]], dtype=torch.float64)
    posed = torch.cat([posed, _box_at(ch, beside)])
    d = hand_part_distances(ch, parts, posed)
    assert d.hands == ("LeftHand", "RightHand") and d.parts == CLUSTERS
    assert not bool(d.measured[0, own_arm]) and not bool(d.measured[1].any())  # own arm; no right hand
    got = d.distance[:, 0, torso]
    expected = [gaps[0] * s, gaps[1] * s, gaps[2] * s, 0.0, 0.0, float(np.hypot(dx, dy))]
    assert torch.allclose(got, torch.tensor(expected, dtype=torch.float64), atol=1e-6), got
    assert d.inside[:, 0, torso].tolist() == [False, False, False, True, True, False]
    assert torch.isinf(d.distance[:, 0, own_arm]).all()
    # Pairs: distinct hand vertices (of the small box) paired with big-box vertices, nearest first.
    hand = parts.part_vertices(parts.index("LeftHand"))
    pairs = d.pairs[:, 0, torso]
    assert torch.isin(pairs[..., 0], hand).all() and not torch.isin(pairs[..., 1], hand).any()
    assert bool((d.pair_distance[:, 0, torso, 1:] >= d.pair_distance[:, 0, torso, :1]).all())
    # Beyond max_distance: inf.
    far = hand_part_distances(ch, parts, _hand_on_top([0.2], ch))
    assert torch.isinf(far.distance[0, 0, torso])


def test_box_hand_contacts_rest_slide_and_release() -> None:
    ch, mapping = two_boxes()
    parts = body_parts(ch, mapping)
    # Resting 0.5 cm above the top and moving with the body: a contact on every frame, 3 closest pairs.
    posed = _hand_on_top([0.005] * 6, ch) + torch.linspace(0, 0.2, 6)[:, None, None] * torch.tensor([1.0, 0.0, 0.0])
    sc = detect_self_contacts(parts, posed, ch.height, 30.0)
    assert sc.count == 6 and sc.frames_with_contact().all()
    assert {sc.part_names[h] for h in sc.hand.tolist()} == {"LeftHand"}
    assert {sc.part_names[o] for o in sc.other.tolist()} == {"Hips"}
    assert {sc.part_clusters[c] for c in sc.part.tolist()} == {"torso"}
    assert sc.pairs.shape == (6, 3, 2) and not bool(sc.intersecting.any())
    assert float(sc.cosine.min()) > 0.9  # moving together
    assert torch.allclose(sc.source_distance, torch.full((6,), 0.005 * ch.height / 1.80), atol=1e-5)
    assert sc.summary() == [{"hand": "LeftHand", "other": "torso", "frames": 6, "first": 0, "last": 5}]
    # Sunk 1 cm in and sliding across the top (only the hand moves): still a contact, intersecting.
    centres = torch.zeros(6, 3)
    centres[:, 1] = BIG + SMALL / 2 - 0.01 * ch.height / 1.80
    centres[:, 0] = torch.linspace(-0.1, 0.1, 6)
    sc = detect_self_contacts(parts, _box_at(ch, centres), ch.height, 30.0)
    assert sc.count == 6 and bool(sc.intersecting.all()) and float(sc.source_distance.max()) == 0.0
    # Hysteresis: lifting to 2 cm after touching stays a contact; hovering at 2 cm without touching is none;
    # beyond 3 cm never; a short lift to 2.8 cm between two touches is filled, one to 4 cm is not.
    cases = [
        ([0.01, 0.02, 0.02, 0.04, 0.02], [True, True, True, False, False]),
        ([0.02, 0.02, 0.02], [False, False, False]),
        ([0.01, 0.028, 0.028, 0.01], [True, True, True, True]),
        ([0.01, 0.04, 0.04, 0.01], [True, False, False, True]),
    ]
    for gaps, expected in cases:
        sc = detect_self_contacts(parts, _hand_on_top(gaps, ch), ch.height, 30.0)
        assert sc.frames_with_contact().tolist() == expected, (gaps, sc.source_distance)


def test_contact_mask_rules() -> None:
    d = torch.tensor([0.05, 0.01, 0.02, 0.024, 0.026, 0.02, 0.0, 0.029, 0.029, 0.0, 0.031, 0.0])[:, None]
    on = contact_mask(d, 1.80, 30.0)[:, 0].tolist()
    assert on == [False, True, True, True, True, True, True, True, True, True, False, True]
    # Gap filling is limited to fill_s (0.2 s: 6 frames at 30 fps).
    gap = torch.tensor([0.0] + [0.028] * 7 + [0.0])[:, None]
    assert contact_mask(gap, 1.80, 30.0)[:, 0].tolist() == [True] + [False] * 7 + [True]
    assert contact_mask(gap, 1.80, 60.0)[:, 0].all()  # 7 frames at 60 fps is under 0.2 s
    # Thresholds scale with the body: 1.2 cm is touching at 1.80 m, not at 0.9 m (0.75 cm threshold).
    assert bool(contact_mask(torch.tensor([[0.012]]), 1.80, 30.0).all())
    assert not bool(contact_mask(torch.tensor([[0.012]]), 0.90, 30.0).any())


@pytest.fixture(scope="module")
def placed(average):
    """The average body with its left hand on the hip, on the cheek, sliding down the thigh (5 frames, the
    arm's rotations slerped between the hand on a high and a low point of the thigh), and in the rest pose."""
    ch, mapping, parts = average

    def pose(local_r: torch.Tensor, local_t: torch.Tensor) -> torch.Tensor:
        grot, gpos = kinematics.forward_kinematics(ch.skeleton.parents, local_r, local_t)
        return ch.pose_vertices(grot, gpos).detach()

    hip = hand_on_vertex_pose(ch, mapping, parts, hip_vertex(ch, parts, "Left"), "Left", gap=0.003, steps=80)
    cheek = hand_on_vertex_pose(ch, mapping, parts, cheek_vertex(ch, parts, "Left"), "Left", gap=-0.003, steps=80)
    high, low = thigh_vertices(ch, parts, "Left", count=2)
    top = hand_on_vertex_pose(ch, mapping, parts, high, "Left", gap=0.004, steps=80)
    bottom = hand_on_vertex_pose(ch, mapping, parts, low, "Left", gap=0.004, steps=80)
    slide = [pose(rot.slerp(top[0], bottom[0], torch.full(top[0].shape[:1], w)), top[1]) for w in np.linspace(0, 1, 5)]
    rr, rp = ch.skeleton.rest_global()
    return {"hip": pose(*hip), "cheek": pose(*cheek), "slide": torch.stack(slide), "rest": ch.pose_vertices(rr, rp)}


def _touched(sc) -> set[str]:  # type: ignore[no-untyped-def]
    return {f"{sc.part_names[h]}-{sc.part_clusters[c]}" for h, c in zip(sc.hand.tolist(), sc.part.tolist(), strict=True)}


def test_hand_on_hip_cheek_and_sliding_on_thigh_are_detected(average, placed) -> None:
    ch, _, parts = average
    # Hip: resting 3 mm off the skin, held for 6 frames while the body walks on.
    posed = placed["hip"][None].repeat(6, 1, 1) + torch.linspace(0, 0.1, 6)[:, None, None] * torch.tensor([0.0, 0.0, 1.0])
    sc = detect_self_contacts(parts, posed, ch.height, 30.0, rest_vertices=ch.vertices)
    assert sc.frames_with_contact().all() and "LeftHand-torso" in _touched(sc), sc.summary()
    assert _touched(sc) <= {"LeftHand-torso", "LeftHand-left_leg"}, sc.summary()
    assert float(sc.source_distance.min()) < 0.01
    # Cheek: pressed 3 mm in (the source body's error): a contact with the head, the hand inside it.
    sc = detect_self_contacts(parts, placed["cheek"][None].repeat(3, 1, 1), ch.height, 30.0)
    head = sc.part == CLUSTERS.index("head")
    assert "LeftHand-head" in _touched(sc) and bool(head.any()) and bool(sc.intersecting[head].all()), sc.summary()
    assert sc.frames_with_contact().all()
    # Sliding down the thigh: the hand moves along it, in contact on every frame.
    slide = placed["slide"]
    hand = parts.part_vertices(parts.index("LeftHand"))
    assert float((slide[-1, hand].mean(0) - slide[0, hand].mean(0)).norm()) > 0.05
    sc = detect_self_contacts(parts, slide, ch.height, 30.0)
    leg = sc.part == CLUSTERS.index("left_leg")
    assert sorted(set(sc.frame[leg].tolist())) == list(range(len(slide))), sc.summary()
    # The pairs touch: hand vertex and thigh vertex within a few centimetres (vertex spacing on the thigh).
    assert float(sc.distance[leg].min(dim=1).values.max()) < 0.05


def test_hands_away_are_not_contacts(average, placed) -> None:
    ch, _, parts = average
    posed = torch.stack([placed["rest"], placed["hip"]])
    d = hand_part_distances(ch, parts, posed)
    assert float(d.nearest()[0].min()) > 0.03  # rest pose: both hands more than 3 cm from everything
    sc = detect_self_contacts(parts, posed, ch.height, 30.0)
    assert sc.frames_with_contact().tolist() == [False, True]
    # The right hand stays at rest beside the body on the hip frame: no contact of it.
    assert {sc.part_names[h] for h in sc.hand.tolist()} == {"LeftHand"}


def test_rest_pose_has_no_self_contact(average) -> None:
    ch, _, parts = average
    rr, rp = ch.skeleton.rest_global()
    posed = ch.pose_vertices(rr, rp)[None].repeat(4, 1, 1)
    assert detect_self_contacts(parts, posed, ch.height, 30.0).count == 0


def test_two_hand_grip_in_swordplay_clip(shared_data: Path) -> None:
    """CMU 02_08 (swordplay): the built-in body driven by the clip holds the sword with both hands."""
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.loading import load_character, load_motion

    source = load_character("builtin:male_average")
    loaded = load_motion(shared_data / "motions" / "cmu" / "002_08.bvh")
    motion, mapping = loaded.motion, loaded.mapping
    copied = copy_retarget(motion, mapping, source.character.skeleton, source.mapping)
    grot, gpos = copied.global_transforms()
    step = 2  # 60 -> 30 fps
    posed = source.character.pose_vertices(grot[150:450:step], gpos[150:450:step])
    sc = detect_self_contacts(body_parts(source.character, source.mapping), posed, source.character.height, copied.fps / step)
    both = [e for e in sc.summary() if (e["hand"], e["other"]) in {("LeftHand", "right_arm"), ("RightHand", "left_arm")}]
    assert both and max(e["frames"] for e in both) >= 20, sc.summary()


# --- foot contacts ----------------------------------------------------------------------------------------


def _foot_mapping() -> JointMapping:
    return JointMapping({"LeftFoot": 0, "LeftToeBase": 1, "RightFoot": 2, "RightToeBase": 3})


def test_foot_planted_then_lifted() -> None:
    f = 40
    rest = torch.tensor([[0.1, 0.08, 0.0], [0.1, 0.03, 0.12], [-0.1, 0.08, 0.0], [-0.1, 0.03, 0.12]])
    pos = rest.repeat(f, 1, 1)
    lift = torch.arange(20, dtype=torch.float32) * 0.015  # 1.5 cm per frame from frame 20 on
    pos[20:, 0, 1] += lift
    pos[20:, 1, 1] += lift
    fc = detect_foot_contacts(pos, rest, _foot_mapping(), height=1.8, fps=30.0)
    lt, lh, rt, rh = fc.labels.T
    assert fc.names == ("left_toe", "left_heel", "right_toe", "right_heel")
    assert lt[:20].all() and not lt[21:].any()  # 1.5 cm/frame > 1 cm: lifted from the first moving frame
    assert lh[:20].all() and not lh[21:].any()
    assert rt.all() and rh.all()  # the right foot stays planted
    # Toe height alone: a toe hovering 4 cm up without moving is not in contact; 2 cm up it is.
    for height, expected in ((0.04, False), (0.02, True)):
        p = rest.repeat(10, 1, 1)
        p[:, 1, 1] += height
        assert bool(detect_foot_contacts(p, rest, _foot_mapping(), 1.8, 30.0).labels[:, 0].all()) == expected


def test_foot_thresholds_scale_with_body_and_frame_rate() -> None:
    rest = torch.zeros(4, 3)
    pos = rest.repeat(30, 1, 1)
    pos[:, 0, 0] = torch.arange(30) * 0.007  # heel slides 7 mm per frame
    mapping = _foot_mapping()
    assert detect_foot_contacts(pos, rest, mapping, 1.8, 30.0).labels[:, 1].all()  # under 1 cm/frame at 30 fps
    assert not detect_foot_contacts(pos, rest, mapping, 1.8, 60.0).labels[:, 1].any()  # 0.5 cm at 60 fps
    assert not detect_foot_contacts(pos, rest, mapping, 0.9, 30.0).labels[:, 1].any()  # half-size body
    missing = detect_foot_contacts(pos, rest, JointMapping({"LeftFoot": 0}), 1.8, 30.0)
    assert missing.available.tolist() == [False, True, False, False] and not missing.labels[:, 0].any()


def test_window_fills_short_gaps_only() -> None:
    x = torch.tensor([1, 1, 0, 1, 1, 0, 0, 0, 1, 1], dtype=torch.bool)[:, None]
    out = fill_window(x, 5)[:, 0].tolist()
    assert out[2] is True  # one missing frame among contacts
    assert out[5:8] == [False, False, False]
    assert fill_window(torch.zeros(0, 4, dtype=torch.bool)).shape == (0, 4)
    assert FootContactParams().window == 5


# --- correspondence ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def skinny_bulky():
    a, b = load_preset("female_skinny"), load_preset("male_bulky")
    return a, mapping_by_name(a.skeleton.names), b, mapping_by_name(b.skeleton.names)


def test_correspondence_between_body_shapes(skinny_bulky) -> None:
    """The MakeHuman bodies share their topology, so vertex i of one is vertex i of the other: the truth."""
    a, ma, b, mb = skinny_bulky
    corr = build_correspondence(a, ma, b, mb)
    idx = corr.map(torch.arange(a.num_vertices))
    err = (b.vertices[idx] - b.vertices).norm(dim=1)
    assert float(err.median()) < 0.015
    parts = body_parts(b, mb)
    for hand in ("LeftHand", "RightHand"):
        assert float(err[parts.group(hand)].median()) < 0.01
    same = build_correspondence(b, mb, b, mb).map(torch.arange(b.num_vertices))
    assert torch.equal(same, torch.arange(b.num_vertices))


def test_correspondence_across_topologies(skinny_bulky) -> None:
    """Target remeshed (each triangle split in four): original vertices keep their index and place."""
    a, ma, b, mb = skinny_bulky
    verts, faces = trimesh.remesh.subdivide(b.vertices.numpy(), b.faces.numpy())
    dense = b.dense_weights().numpy()
    edges = np.sort(np.concatenate([b.faces.numpy()[:, [0, 1]], b.faces.numpy()[:, [1, 2]], b.faces.numpy()[:, [2, 0]]]), axis=1)
    edges = np.unique(edges, axis=0)
    # Each new vertex is the midpoint of an edge: it takes the mean of the edge's two skinning weights.
    from scipy.spatial import cKDTree

    dist, which = cKDTree(b.vertices.numpy()[edges].mean(1)).query(verts[len(dense) :])
    assert dist.max() < 1e-6
    w = torch.tensor(np.concatenate([dense, dense[edges[which]].mean(1)]), dtype=torch.float32)
    j = torch.arange(w.shape[1]).repeat(len(w), 1)
    fine = Character("fine", b.skeleton, torch.tensor(verts, dtype=torch.float32), torch.tensor(faces), j, w)
    idx = build_correspondence(a, ma, fine, mb).map(torch.arange(a.num_vertices))
    err = (fine.vertices[idx] - b.vertices).norm(dim=1)
    assert float(err.median()) < 0.015


def test_transfer_contacts_maps_every_pair(skinny_bulky) -> None:
    ch, mapping = two_boxes()
    parts = body_parts(ch, mapping)
    grot, gpos = box_pose(0.01, 3)
    sc = detect_self_contacts(parts, ch.pose_vertices(grot, gpos), ch.height, 30.0)
    corr = build_correspondence(ch, mapping, ch, mapping)
    cons = transfer_contacts(sc, corr)
    assert cons.count == sc.count * 3
    assert torch.equal(cons.i, sc.pairs[..., 0].reshape(-1)) and torch.equal(cons.j, sc.pairs[..., 1].reshape(-1))
    assert torch.equal(cons.frame, sc.frame.repeat_interleave(3))
    part = cons.select_frames(1, 3)
    assert part.num_frames == 2 and part.count == 6 and int(part.frame.max()) == 1


# --- hand-to-part distances against brute force ----------------------------------------------------------


def _winding(p: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """Generalized winding number ``(N,)`` of points ``p (N, 3)`` for the closed triangles ``tri (T, 3, 3)``
    (Van Oosterom and Strackee's solid angle; about 1 inside, 0 outside whatever the orientation's sign)."""
    out = torch.zeros(len(p), dtype=p.dtype)
    for s in range(0, len(p), 64):
        a, b, c = (tri[None, :, k] - p[s : s + 64, None] for k in range(3))  # (n, T, 3)
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        num = (a * torch.linalg.cross(b, c)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
        out[s : s + 64] = (2 * torch.atan2(num, den)).sum(1).abs() / (4 * np.pi)
    return out


def _brute_vertex_distances(p: torch.Tensor, tri: torch.Tensor, reach: float) -> torch.Tensor:
    """Exact distance ``(N,)`` of each point of ``p (N, 3)`` to the triangles ``tri (T, 3, 3)``, inf beyond
    ``reach``: every (point, triangle) pair whose bounding sphere is within reach, no other culling."""
    from retarget_core.geometry.closest_point import closest_points

    centre = tri.mean(1)
    radius = (tri - centre[:, None]).norm(dim=-1).amax(-1)
    out = torch.full((len(p),), float("inf"), dtype=p.dtype)
    for s in range(0, len(p), 256):
        i, t = torch.nonzero(torch.cdist(p[s : s + 256], centre) - radius <= reach, as_tuple=True)
        q = closest_points(p[s + i], tri[t, 0], tri[t, 1], tri[t, 2])
        d = (p[s + i] - q).norm(dim=-1)
        out[s : s + 256] = torch.full((min(256, len(p) - s),), float("inf"), dtype=p.dtype).scatter_reduce(0, i, d, "amin")
    return out


def _check_against_brute_force(geom, x: torch.Tensor, got, f: int) -> int:  # type: ignore[no-untyped-def]
    """Asserts frame ``f`` of ``got`` (HandPartDistances) on the posed frame ``x (V, 3)``; returns the number of
    (hand, part) pairs found within the cutoff."""
    cutoff, slack = got.max_distance, 0.005 * got.max_distance / 0.05
    centres = torch.zeros(len(geom.ring_count), 3, dtype=x.dtype).index_add_(0, geom.ring_cap, x[geom.ring_vertex])
    ext = torch.cat([x, centres / geom.ring_count.clamp_min(1).to(x.dtype)[:, None]])
    near = 0
    for h, hv in enumerate(geom.hand_vertices):
        for c in range(len(geom.parts)):
            if not bool(geom.measured[h, c]):
                assert torch.isinf(got.distance[f, h, c])
                continue
            tri = ext[geom.faces[geom.face_part == c]]
            dv = _brute_vertex_distances(x[hv], tri, cutoff + slack)
            dmin = float(dv.min())
            cand = dv <= cutoff
            wind = _winding(x[hv][cand], tri) if bool(cand.any()) else torch.zeros(0, dtype=x.dtype)
            inside_any = bool((wind > 0.5).any())
            inside_near = bool((wind[dv[cand] <= dmin + slack] > 0.5).any())
            d, ins = float(got.distance[f, h, c]), bool(got.inside[f, h, c])
            assert ins == (d == 0.0)
            assert not ins or inside_any, (f, h, c)  # inside only where a hand vertex is inside
            assert ins or not inside_near, (f, h, c)  # a vertex inside within the slack of the closest is seen
            if ins or dmin <= cutoff:
                near += 1
                assert ins or d == pytest.approx(dmin, abs=1e-12), (f, h, c, d, dmin)
                k = got.pairs.shape[-2]
                want = torch.sort(dv).values[:k]
                assert torch.allclose(got.pair_distance[f, h, c], want, atol=1e-12), (f, h, c)
                hand_local = geom.hand_local[got.pairs[f, h, c, :, 0]]
                assert torch.allclose(dv[hand_local], want, atol=1e-12)
                assert bool(((got.pairs[f, h, c, :, 1] >= 0) & (got.pairs[f, h, c, :, 1] < geom.num_vertices)).all())
            else:
                assert d == float("inf") and bool((got.pairs[f, h, c] == -1).all()), (f, h, c, d, dmin)
    return near


def test_hand_part_distances_match_brute_force(average, placed) -> None:
    """Every distance, inside flag and closest pair of the culled search equals an uncull brute force (exact
    point-triangle distances of every pair in reach, inside by winding number) on hand poses near the body."""
    from retarget_core.contacts.hand_distance import hand_part_geometry

    ch, _, parts = average
    posed = torch.stack([placed["hip"], placed["cheek"], placed["slide"][0], placed["slide"][3], placed["rest"]])
    posed = posed.double()
    geom = hand_part_geometry(parts, ch.vertices, ch.height)
    got = hand_part_distances(None, parts, posed, geometry=geom, height=ch.height)
    near = sum(_check_against_brute_force(geom, posed[f], got, f) for f in range(len(posed)))
    assert near >= 4 and bool(got.inside[1, 0].any())  # the cheek frame: the left hand sunk into the head


def test_hand_part_distances_with_a_cutoff_per_group() -> None:
    """Each (frame, hand, part) measured up to its own cutoff (what the metrics ask): the full query's distance
    where it lies within that cutoff, inf beyond it and where the cutoff is 0 (not measured)."""
    ch, mapping = two_boxes(torch.float64)
    parts = body_parts(ch, mapping)
    torso, s = CLUSTERS.index("torso"), ch.height / 1.80
    posed = _hand_on_top([0.002, 0.01, 0.03, -0.01], ch)  # at 1.80 m: 2 mm, 1 cm and 3 cm above, sunk in
    full = hand_part_distances(ch, parts, posed)
    cutoffs = torch.zeros(full.distance.shape, dtype=torch.float64)
    cutoffs[:, 0, torso] = torch.tensor([0.005, 0.005, 0.05, 0.05]) * s  # frame 1 beyond its cutoff
    got = hand_part_distances(ch, parts, posed, cutoffs=cutoffs)
    expected = torch.tensor([0.002 * s, float("inf"), 0.03 * s, 0.0], dtype=torch.float64)
    assert torch.allclose(got.distance[:, 0, torso], expected, atol=1e-6), got.distance[:, 0, torso]
    assert torch.equal(got.distance[[0, 2, 3], 0, torso], full.distance[[0, 2, 3], 0, torso])
    assert got.inside[:, 0, torso].tolist() == [False, False, False, True]
    others = torch.ones(full.distance.shape, dtype=torch.bool)
    others[:, 0, torso] = False
    assert bool(torch.isinf(got.distance[others]).all())  # cutoff 0: not measured



def test_hand_part_distances_do_not_depend_on_the_chunks(samples: Path) -> None:
    """Chunk sizes are efficiency only: coarse and fine chunks give the same distances, inside flags and closest
    pairs. On these frames of the sample clip a hand vertex's closest point lies on an edge two triangles share,
    and the pair's body vertex read from the first of them walked differed with the chunks (now the lowest index)."""
    from retarget_core.contacts.hand_distance import HandDistanceParams, hand_part_geometry
    from retarget_core.jobs import JobInputs
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import prepare

    inputs = JobInputs(samples / "motions" / "007_03.bvh", str(samples / "characters" / "mh_male_bulky.glb"),
                       options=RetargetOptions(fps=30.0))  # fmt: skip
    prepared = prepare(inputs)
    ch, parts = prepared.target.character, prepared.assets.parts
    posed = ch.pose_vertices(*prepared.before.global_transforms())[[12, 15, 82, 97]].double()
    results = []
    for hand_edges, triangle_edges in ((6.0, 4.0), (2.0, 12.0), (12.0, 2.0)):
        params = HandDistanceParams(hand_chunk_edges=hand_edges, triangle_chunk_edges=triangle_edges)
        geom = hand_part_geometry(parts, ch.vertices, ch.height, params)
        results.append(hand_part_distances(ch, parts, posed, params=params, geometry=geom))
    assert int(torch.isfinite(results[0].distance).sum()) >= 4
    for other in results[1:]:
        for a, b in ((results[0].distance, other.distance), (results[0].inside, other.inside),
                     (results[0].pairs, other.pairs), (results[0].pair_distance, other.pair_distance)):  # fmt: skip
            assert torch.equal(a, b)
