"""Built-in MakeHuman bodies: presets, generator invariants, and agreement with the shared mh_*.glb characters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydantic
import pygltflib
import pytest
import torch
import trimesh

from retarget_core import rotations as rot
from retarget_core.bodies import (
    BodyParams,
    list_presets,
    load_preset,
    make_body,
    makehuman,
    preset_params,
    sample_body_params,
)
from retarget_core.canonical import CANONICAL_JOINTS, CANONICAL_PARENT
from retarget_core.character import Character

REQUIRED_PRESETS = [
    "male_average", "male_skinny", "male_muscular", "male_bulky",
    "female_average", "female_skinny", "neutral_tall", "child",
]  # fmt: skip
SHARED_NAMES = [n for n in REQUIRED_PRESETS if n != "child"]
BODY_VERTICES = 13_380
BODY_TRIANGLES = 26_756


def _positions(c: Character) -> np.ndarray:
    return c.skeleton.rest_global()[1].numpy()


def _mesh(c: Character) -> trimesh.Trimesh:
    return trimesh.Trimesh(c.vertices.numpy(), c.faces.numpy(), process=False)


def _waist_circumference(c: Character) -> float:
    """Perimeter of the horizontal cross-section through Spine1 that encloses the Spine1 joint."""
    centre = _positions(c)[c.skeleton.index("Spine1")]
    section = _mesh(c).section(plane_origin=centre, plane_normal=[0.0, 1.0, 0.0])
    assert section is not None
    for loop in section.discrete:
        xz = loop[:, [0, 2]]
        px, pz = centre[0], centre[2]
        inside = False
        for a, b in zip(xz, np.roll(xz, -1, axis=0), strict=True):
            if (a[1] > pz) != (b[1] > pz) and a[0] + (pz - a[1]) * (b[0] - a[0]) / (b[1] - a[1]) > px:
                inside = not inside
        if inside:
            return float(np.linalg.norm(np.diff(np.vstack([loop, loop[:1]]), axis=0), axis=1).sum())
    raise AssertionError("no cross-section loop encloses the waist")


def _read_glb(path: Path) -> dict[str, np.ndarray | list[str]]:
    """Positions, triangles, joint names, joint world positions and dense weights of a shared character."""
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    assert blob is not None

    def acc(i: int) -> np.ndarray:
        a = g.accessors[i]
        view = g.bufferViews[a.bufferView]
        dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32, 5121: np.uint8}[a.componentType]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
        return np.frombuffer(blob, dtype, a.count * width, view.byteOffset + (a.byteOffset or 0)).reshape(
            a.count, width
        )

    prim = g.meshes[0].primitives[0]
    skin = g.skins[0]
    ibm = acc(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major in glTF
    joints = acc(prim.attributes.JOINTS_0).astype(np.int64)
    weights = acc(prim.attributes.WEIGHTS_0).astype(np.float64)
    dense = np.zeros((len(joints), len(skin.joints)))
    np.add.at(dense, (np.repeat(np.arange(len(joints)), joints.shape[1]), joints.ravel()), weights.ravel())
    return {
        "positions": acc(prim.attributes.POSITION).astype(np.float64),
        "triangles": acc(prim.indices).reshape(-1, 3).astype(np.int64),
        "names": [g.nodes[j].name for j in skin.joints],
        "joints": np.linalg.inv(ibm)[:, :3, 3],
        "weights": dense,
    }


@pytest.fixture(scope="module", params=REQUIRED_PRESETS)
def preset(request: pytest.FixtureRequest) -> tuple[str, Character]:
    return request.param, load_preset(request.param)


def test_required_presets_are_listed() -> None:
    assert set(REQUIRED_PRESETS) <= set(list_presets())
    assert list_presets() == sorted(list_presets())


def test_unknown_preset_names_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="male_average") as err:
        load_preset("giant")
    assert "giant" in str(err.value)
    assert all(name in str(err.value) for name in REQUIRED_PRESETS)


def test_preset_skeleton_is_canonical(preset: tuple[str, Character]) -> None:
    _, c = preset
    sk = c.skeleton
    assert sk.names == list(CANONICAL_JOINTS)
    for j, name in enumerate(sk.names):
        parent = CANONICAL_PARENT[name]
        assert sk.parents[j] == (-1 if parent is None else sk.index(parent))
    # Rest rotations are identity in world space.
    world_rot, _ = sk.rest_global()
    assert torch.allclose(world_rot, rot.identity(sk.num_joints), atol=1e-6)


def test_preset_mesh_is_the_closed_body(preset: tuple[str, Character]) -> None:
    _, c = preset
    assert c.num_vertices == BODY_VERTICES
    assert tuple(c.faces.shape) == (BODY_TRIANGLES, 3)
    assert c.faces.dtype == torch.int64
    mesh = _mesh(c)
    assert mesh.is_watertight, "the body is not a closed surface"
    assert mesh.is_winding_consistent
    assert len(mesh.split(only_watertight=False)) == 1
    assert mesh.volume > 0.01  # outward normals, at least 10 litres


def test_preset_height_feet_and_facing(preset: tuple[str, Character]) -> None:
    name, c = preset
    requested = preset_params(name).height
    assert requested is not None
    assert abs(c.height - requested) < 0.02
    assert abs(float(c.vertices[:, 1].min())) < 1e-3
    p = _positions(c)
    idx = c.skeleton.index
    for side in ("Left", "Right"):
        assert p[idx(f"{side}ToeBase"), 2] > p[idx(f"{side}Foot"), 2] + 0.05, "toes must be in front (+Z) of the ankle"
        assert p[idx(f"{side}Foot"), 1] < p[idx(f"{side}Leg"), 1] < p[idx(f"{side}UpLeg"), 1]
    assert p[idx("Head"), 1] > p[idx("Neck"), 1] > p[idx("Spine2"), 1] > p[idx("Hips"), 1]
    assert abs(p[idx("Hips"), 0]) < 1e-6 and abs(p[idx("Hips"), 2]) < 1e-6
    # The character's left is +X; A-pose: hands below the shoulders, away from the body.
    for j, jname in enumerate(CANONICAL_JOINTS):
        if jname.startswith("Left"):
            assert p[j, 0] > 0.02, jname
            assert p[idx("Right" + jname[4:]), 0] < -0.02, jname
    for side in ("Left", "Right"):
        arm, hand = p[idx(f"{side}Arm")], p[idx(f"{side}Hand")]
        assert hand[1] < arm[1] - 0.1 and abs(hand[0]) > abs(arm[0]) + 0.1


def test_preset_skin_weights(preset: tuple[str, Character]) -> None:
    _, c = preset
    assert tuple(c.skin_joints.shape) == (BODY_VERTICES, 4) == tuple(c.skin_weights.shape)
    assert int(c.skin_joints.min()) >= 0 and int(c.skin_joints.max()) < len(CANONICAL_JOINTS)
    assert float(c.skin_weights.min()) >= 0.0
    assert torch.allclose(c.skin_weights.sum(dim=1), torch.ones(BODY_VERTICES), atol=1e-5)
    # Every joint drives some vertices, which lie around it and on its side (weighted by its weights).
    dense = c.dense_weights().numpy()
    verts = c.vertices.numpy()
    p = _positions(c)
    for j, name in enumerate(CANONICAL_JOINTS):
        w = dense[:, j]
        assert np.sum(w > 0.05) > 50, f"{name} drives only {np.sum(w > 0.05)} vertices"
        centroid = (w[:, None] * verts).sum(axis=0) / w.sum()
        assert np.linalg.norm(centroid - p[j]) < 0.2 * c.height, name
        if name.startswith("Left"):  # the midline seam may be a few mm off x = 0
            assert w[verts[:, 0] < -0.01].sum() < 1e-3 * w.sum(), name
        if name.startswith("Right"):
            assert w[verts[:, 0] > 0.01].sum() < 1e-3 * w.sum(), name
    owner = [CANONICAL_JOINTS[j] for j in dense.argmax(axis=1)]
    assert owner[verts[:, 1].argmax()] == "Head"
    assert owner[verts[:, 0].argmax()] == "LeftHand"  # fingertips, A-pose
    assert owner[verts[:, 0].argmin()] == "RightHand"
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        low = np.flatnonzero((verts[:, 1] < 0.05) & (sign * verts[:, 0] > 0))
        assert owner[low[verts[low, 2].argmax()]] in (f"{side}ToeBase", f"{side}Foot")  # tip of the toes


def test_bulky_is_larger_than_skinny() -> None:
    bulky, skinny = load_preset("male_bulky"), load_preset("male_skinny")
    assert _waist_circumference(bulky) > _waist_circumference(skinny) + 0.1
    assert _mesh(bulky).volume > _mesh(skinny).volume * 1.3
    # Same at equal height: weight alone makes the waist and the volume grow, the height is unchanged.
    bodies = [make_body(BodyParams(gender=1.0, weight=w, height=1.8)) for w in (0.0, 0.5, 1.0)]
    assert max(b.height for b in bodies) - min(b.height for b in bodies) < 1e-4
    waists = [_waist_circumference(b) for b in bodies]
    volumes = [_mesh(b).volume for b in bodies]
    assert waists[0] < waists[1] < waists[2] and waists[2] > waists[0] + 0.05
    assert volumes[0] < volumes[1] < volumes[2] and volumes[2] > 1.1 * volumes[0]


def test_height_is_reached_by_macro_then_scale() -> None:
    tall = BodyParams(gender=1.0, height=1.95)
    _, macro = makehuman.shaped_vertices(tall)
    assert 0.5 < macro <= 1.0  # taller than the natural 1.73 m: the height macro grows
    _, macro = makehuman.shaped_vertices(BodyParams(gender=0.0, height=1.45))
    assert 0.0 <= macro < 0.5
    # Beyond what the macro reaches (a one-year-old 1.5 m tall) the scale does the rest.
    baby = make_body(BodyParams(age=1.0, height=1.5))
    assert abs(baby.height - 1.5) < 1e-3
    natural = make_body(BodyParams(gender=1.0))
    assert 1.6 < natural.height < 1.85


def test_macro_weights_follow_makehuman() -> None:
    assert makehuman.age_years_to_macro(1) == 0.0
    assert makehuman.age_years_to_macro(11) == pytest.approx(0.1875)
    assert makehuman.age_years_to_macro(25) == pytest.approx(0.5)
    assert makehuman.age_years_to_macro(90) == 1.0
    assert makehuman.age_macro_to_years(makehuman.age_years_to_macro(40.0)) == pytest.approx(40.0)
    assert makehuman.anchor_weights("age", 0.5) == {"young": 1.0}
    assert makehuman.anchor_weights("age", 0.75) == pytest.approx({"young": 0.5, "old": 0.5})
    assert makehuman.anchor_weights("weight", 0.25) == pytest.approx({"minweight": 0.5, "averageweight": 0.5})
    assert makehuman.anchor_weights("height", 0.5) == {"": 1.0}
    assert makehuman.anchor_weights("gender", 0.3) == pytest.approx({"female": 0.7, "male": 0.3})
    targets = dict(
        makehuman.macro_targets(
            {"gender": 1.0, "age": 0.5, "muscle": 0.5, "weight": 1.0, "height": 0.5, "proportions": 1.0}
        )
    )
    md = makehuman.MACRO_DIR
    assert targets[f"{md}/universal-male-young-averagemuscle-maxweight"] == pytest.approx(1.0)
    assert targets[f"{md}/proportions/male-young-averagemuscle-maxweight-idealproportions"] == pytest.approx(1.0)
    assert targets[f"{md}/caucasian-male-young"] == pytest.approx(1 / 3)
    assert not any("/height/" in t for t in targets)
    for variable in makehuman.MACRO_ANCHORS:
        for value in np.linspace(0, 1, 9):
            assert sum(makehuman.anchor_weights(variable, float(value)).values()) == pytest.approx(1.0)


def test_params_are_validated() -> None:
    with pytest.raises(pydantic.ValidationError):
        BodyParams(gender=1.5)
    with pytest.raises(pydantic.ValidationError):
        BodyParams(age=0.2)
    with pytest.raises(pydantic.ValidationError):
        BodyParams(height=4.0)
    with pytest.raises(pydantic.ValidationError):
        BodyParams(shoe_size=44)  # type: ignore[call-arg]


def test_generation_is_deterministic_and_cache_returns_copies() -> None:
    params = BodyParams(name="det", gender=0.3, age=47.0, weight=0.7, muscle=0.35, proportions=0.8, height=1.66)
    uncached = makehuman._shape.__wrapped__
    a, b = uncached(params), uncached(params)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.joints, b.joints)
    first = make_body(params)
    first.vertices += 1.0
    first.skin_weights *= 2.0
    first.skeleton.rest_translations.zero_()
    second = make_body(params)
    assert np.array_equal(second.vertices.numpy(), a.vertices)
    assert torch.allclose(second.skin_weights.sum(dim=1), torch.ones(second.num_vertices), atol=1e-5)
    assert np.allclose(second.skeleton.rest_global()[1].numpy(), a.joints, atol=1e-6)
    assert second.name == "det"


def test_sampled_bodies_are_valid() -> None:
    rng = np.random.default_rng(7)
    draws = [sample_body_params(rng) for _ in range(200)]
    again = np.random.default_rng(7)
    assert [sample_body_params(again) for _ in range(3)] == draws[:3]
    heights = np.array([d.height for d in draws], dtype=float)
    ages = np.array([d.age for d in draws])
    assert heights.min() > 1.0 and heights.max() < 2.1
    assert 1.55 < np.median(heights[ages >= 18]) < 1.8
    assert 0 < np.sum(ages < 18) < 60
    assert np.std([d.gender for d in draws]) > 0.2
    for params in draws[:3]:
        c = make_body(params)
        assert params.height is not None and abs(c.height - params.height) < 0.02
        assert abs(float(c.vertices[:, 1].min())) < 1e-3
        assert torch.allclose(c.skin_weights.sum(dim=1), torch.ones(c.num_vertices), atol=1e-5)
        assert _mesh(c).is_watertight


@pytest.mark.parametrize("name", SHARED_NAMES)
def test_presets_match_shared_characters(shared_data: Path, name: str) -> None:
    path = shared_data / "characters" / f"mh_{name}.glb"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    ref = _read_glb(path)
    c = load_preset(name)
    assert ref["names"] == list(CANONICAL_JOINTS)
    assert np.array_equal(ref["triangles"], c.faces.numpy())
    assert np.abs(ref["positions"] - c.vertices.numpy()).max() < 1e-3
    assert np.abs(ref["joints"] - _positions(c)).max() < 1e-3
    assert np.abs(ref["weights"] - c.dense_weights().numpy()).max() < 1e-4
