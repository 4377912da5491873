"""Real production characters as targets: public rigs that are not MakeHuman bodies (stylised proportions,
several meshes, fingers, Blender IK layouts, a VRM 0.x humanoid map), each loaded, mapped, sorted into body and
accessory meshes, and retargeted by a short default job whose GLB animates the fingers as the source does.

The rigs and their licences are listed in retarget_core/data/samples/rigs/README.md; they are read from that
folder or from the shared data's ``rigs/`` (the tests skip, saying "shared", where neither has them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pygltflib
import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.canonical import FINGERS, JointMapping
from retarget_core.io.gltf_read import read_gltf
from retarget_core.jobs import JobInputs, JobOutputs
from retarget_core.loading import LoadedCharacter, load_character, load_motion
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import run_job
from tests import gltf_validator
from tests.conftest import SAMPLES, shared_data_dir

FRAMES = 30
SOURCE = SAMPLES / "motions" / "007_03.bvh"  # CMU 07_03 on a Reallusion rig: 5 fingers x 3 segments
FINGER_FOLLOW_DEG = 2.0
"""Largest difference between the source's and a result's turn of a finger joint since frame 0 (issue 21's
same-convention bound; the rest-aligned copy turns a finger by the source's turn seen from its parent). The
result's turn is seen from the joint mapped as the source finger's parent: the finger's own parent, or the hand
for a thumb that hangs from the forearm (the Cleric's)."""


@dataclass(frozen=True)
class Rig:
    """A real rig and what it must give: file, the joint of each extra joint found, the role of each mesh."""

    file: str
    extras: dict[str, str]
    roles: dict[str, str]
    notes: tuple[str, ...] = field(default=())


def _fingers(names: dict[str, str], sides: dict[str, str]) -> dict[str, str]:
    """Extra name -> joint name for both hands from per-finger templates (``{s}`` is the side's suffix)."""
    return {f"{side}Hand{k}": v.format(s=suffix) for side, suffix in sides.items() for k, v in names.items()}


CRYPTOVOXELS = Rig(
    "cryptovoxels.vrm",
    _fingers(
        {"Thumb1": "Thumb0_{s}", "Thumb2": "Thumb1_{s}", "Thumb3": "Thumb2_{s}"}
        | {
            f"{f}{k}": f"{n}Finger{k}_{{s}}"
            for f, n in (("Index", "Index"), ("Middle", "Middle"), ("Ring", "Ring"), ("Pinky", "Little"))
            for k in (1, 2, 3)
        },
        {"Left": "L", "Right": "R"},
    ),  # fmt: skip
    {"Body": "body"},
)
WITCH = Rig(
    "quaternius_witch.gltf",
    _fingers({f"{f}{k}": f"{f}{k}.{{s}}" for f in FINGERS for k in (1, 2, 3)}, {"Left": "L", "Right": "R"}),
    {"Witch_Body": "body", "Witch_Feet": "body", "Witch_Head": "body", "Witch_Legs": "body"},
    ("'Foot.L' hangs beside the body", "'Foot.R' hangs beside the body"),
)
CLERIC = Rig(
    "quaternius_cleric.gltf",
    _fingers(
        {"Thumb1": "Thumb1.{s}", "Thumb2": "Thumb2.{s}", "Middle1": "Fist1.{s}", "Middle2": "Fist2.{s}"},
        {"Left": "L", "Right": "R"},
    ),  # mitten hands: the fused block Fist1/Fist2 is the middle finger; the thumbs hang from the forearm
    {"Cleric": "body", "Head": "accessory", "Cleric_Staff": "accessory", "ShoulderPads": "accessory"},
    ("'Foot.L' hangs beside the body", "'Foot.R' hangs beside the body"),
)
RIGS = (CRYPTOVOXELS, WITCH, CLERIC)


def rig_path(name: str) -> Path:
    """The rig file from the shipped samples or the shared data's rigs/; skips (saying "shared") without it."""
    shared = shared_data_dir()
    for folder in (SAMPLES / "rigs", shared / "rigs" if shared is not None else None):
        if folder is not None and (folder / name).is_file():
            return folder / name
    pytest.skip(f"{name} is in neither retarget_core/data/samples/rigs nor the shared data's rigs/ folder")


@pytest.fixture(scope="module", params=RIGS, ids=lambda r: r.file)
def loaded(request: pytest.FixtureRequest) -> tuple[Rig, LoadedCharacter]:
    rig: Rig = request.param
    return rig, load_character(rig_path(rig.file))


def test_rig_loads_as_a_character_on_its_feet(loaded: tuple[Rig, LoadedCharacter]) -> None:
    rig, lc = loaded
    c = lc.character
    assert not lc.mapping.missing(), lc.mapping.warnings
    assert 1.2 < c.height < 3.5 and float(c.vertices[:, 1].min()) == pytest.approx(0.0, abs=0.02)
    assert all(any(n in note for note in lc.notes) for n in rig.notes), lc.notes


def test_every_extra_joint_is_found_on_its_side_and_finger(loaded: tuple[Rig, LoadedCharacter]) -> None:
    rig, lc = loaded
    names = lc.character.skeleton.names
    assert {e: names[j] for e, j in lc.mapping.extras.items()} == rig.extras  # these rigs have no toes or twists


def test_meshes_are_sorted_into_body_and_accessories(loaded: tuple[Rig, LoadedCharacter]) -> None:
    rig, lc = loaded
    assert {m.name: m.role for m in lc.character.meshes} == rig.roles


def test_cleric_thumbs_are_found() -> None:
    """The Cleric's thumbs hang from the forearm, beside the fist: mapped as the thumbs, and the report says where
    they hang; its mitten segments are the middle finger, and the staff's joint on Fist1.R is named."""
    lc = load_character(rig_path(CLERIC.file))
    assert {"LeftHandThumb1", "RightHandThumb1"} <= set(lc.mapping.extras)
    warnings = lc.mapping.report(lc.character.skeleton.names)["warnings"]
    assert isinstance(warnings, list)
    for side in ("L", "R"):
        assert any(f"'Thumb1.{side}', 'Thumb2.{side}' hang from the forearm 'LowerArm.{side}'" in w for w in warnings)
        assert any(f"mitten ('Fist1.{side}', 'Fist2.{side}'" in w for w in warnings)
    assert any("'Weapon.R' (a held prop?) hangs from 'Fist1.R'" in w for w in warnings)


_JOBS: dict[str, JobOutputs] = {}


def run_rig_job(rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> JobOutputs:
    """The short default job of 007_03 onto ``rig`` (run once per test session)."""
    if rig.file not in _JOBS:
        out = tmp_path_factory.mktemp(Path(rig.file).stem)
        options = RetargetOptions(frame_end=FRAMES)
        _JOBS[rig.file] = run_job(JobInputs(SOURCE, rig_path(rig.file), options=options), out)
    return _JOBS[rig.file]


@pytest.mark.parametrize("rig", RIGS, ids=lambda r: r.file)
def test_default_job_writes_a_valid_glb_and_metrics(rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> None:
    outputs = run_rig_job(rig, tmp_path_factory)
    gltf_validator.assert_valid_glb(outputs.result_glb)
    metrics = json.loads(outputs.metrics_json.read_text())
    assert metrics["frames"] == FRAMES
    assert {m["name"]: m["role"] for m in metrics["meshes"]} == rig.roles


@pytest.mark.parametrize("rig", RIGS, ids=lambda r: r.file)
def test_result_keys_every_frame_of_the_driven_joints_only(rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Mapped fingers are keyed on every frame; joints the source does not drive (pole targets, finger tips, the
    Cleric's staff joint) are written once."""
    outputs = run_rig_job(rig, tmp_path_factory)
    lc = load_character(rig_path(rig.file))
    sk = lc.character.skeleton
    g = pygltflib.GLTF2().load(str(outputs.result_glb))
    anim = g.animations[0]
    keyed = {g.nodes[c.target.node].name for c in anim.channels if c.target.path == "rotation"
             and g.accessors[anim.samplers[c.sampler].input].count == FRAMES}  # fmt: skip
    driven = {sk.names[j] for j in [*lc.mapping.joints.values(), *lc.mapping.extras.values()]}
    assert set(rig.extras.values()) <= keyed
    assert not keyed - driven - {n for n, p in zip(sk.names, sk.parents, strict=True) if p < 0}


def _finger_gaps(rig: Rig, glb: Path) -> dict[str, torch.Tensor]:
    """Per mapped finger, ``(F,)`` degrees between the source's turn since frame 0 and the GLB's, each seen from
    the joint mapped as the source finger's parent (module doc of :data:`FINGER_FOLLOW_DEG`); fails unless the
    source's fingers do move in these frames."""
    source = load_motion(SOURCE)
    motion = read_gltf(glb).motions[0]
    assert motion.num_frames == FRAMES and motion.fps == source.motion.fps
    sk, target = motion.skeleton, load_character(rig_path(rig.file))
    grot = motion.global_transforms()[0]
    gaps, turned = {}, 0.0
    for extra, joint in rig.extras.items():
        src_joint = source.mapping.extras[extra]
        src_turn = _turn(source.motion.rotations[:FRAMES, src_joint])
        j, ref = sk.index(joint), _mapped_as(source.mapping, source.motion.skeleton.parents[src_joint], target)
        seen = rot.mul(rot.inv(grot[:, sk.parents[j] if ref is None else sk.index(ref)]), grot[:, j])
        gaps[extra] = (src_turn - _turn(seen)).abs()
        turned = max(turned, float(src_turn.max()))
    assert turned > 5.0
    return gaps


@pytest.mark.parametrize("rig", [r for r in RIGS if r.extras], ids=lambda r: r.file)
def test_copy_fingers_follow_the_source_on_every_frame(rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> None:
    """The "before" GLB: the rest-aligned copy turns each finger as the source does."""
    gaps = _finger_gaps(rig, run_rig_job(rig, tmp_path_factory).before_glb)
    assert {e: round(float(g.max()), 2) for e, g in gaps.items() if g.max() > FINGER_FOLLOW_DEG} == {}


@pytest.mark.parametrize("rig", [r for r in RIGS if r.extras], ids=lambda r: r.file)
def test_result_fingers_follow_the_source(rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> None:
    """The result GLB, default chain (finger clearance on): each finger follows the source on every frame."""
    gaps = _finger_gaps(rig, run_rig_job(rig, tmp_path_factory).result_glb)
    assert {e: round(float(g.max()), 2) for e, g in gaps.items() if g.max() > FINGER_FOLLOW_DEG} == {}


def _mapped_as(source_map: JointMapping, joint: int, target: LoadedCharacter) -> str | None:
    """The name of the target joint mapped as the source's ``joint`` (a hand, a finger), None if none is."""
    names = {j: n for n, j in [*source_map.joints.items(), *source_map.extras.items()]}
    mapped = {**target.mapping.joints, **target.mapping.extras}.get(names.get(joint, ""))
    return None if mapped is None else target.character.skeleton.names[mapped]


def _turn(local: torch.Tensor) -> torch.Tensor:
    """``(F,)`` degrees each frame's local rotation ``(F, 4)`` has turned since frame 0."""
    d = rot.mul(local, rot.inv(local[:1].expand_as(local)))
    return torch.rad2deg(2 * torch.atan2(d[..., :3].norm(dim=-1), d[..., 3].abs()))


# ----- the conventions of these rigs on constructed cases (no shared data needed) -------------------------------------
CATS = """
Hips 0 100 0
  {Side} leg 9 -5 0
    {Side} knee 0 -45 0
      {Side} ankle 0 -42 0
        {Side} toe 0 -5 12
  Spine 0 10 0
    Chest 0 20 0
      Neck 0 25 0
        Head 0 10 0
      {Side} shoulder 4 20 0
        {Side} arm 10 0 0
          {Side} elbow 27 0 0
            {Side} wrist 25 0 0
              Thumb0_{S} 3 -1 3
                Thumb1_{S} 3 0 1
                  Thumb2_{S} 2 0 1
              IndexFinger1_{S} 9 0 2
                IndexFinger2_{S} 4 0 0
                  IndexFinger3_{S} 3 0 0
"""


def test_vrm_humanoid_map_holds_the_body_and_names_fill_the_fingers_it_lacks() -> None:
    """As in cryptovoxels.vrm: MMD/Cats names ('Left leg' is the thigh) that the names alone misread, a VRM 0.x
    bone map that names the legs and the first two index joints but no thumb: the map holds the body joints
    (method 'vrm'), the names add the thumbs and the distal index joint, and a warning says so."""
    from retarget_core.mapping import map_joints
    from tests.core.test_mapping import rig

    sk = rig(CATS)
    body = {"Hips": "Hips", "Spine": "Spine", "Neck": "Neck", "Head": "Head"}
    for side in ("Left", "Right"):
        for canonical, joint in (
            ("UpLeg", "leg"),
            ("Leg", "knee"),
            ("Foot", "ankle"),
            ("ToeBase", "toe"),
            ("Shoulder", "shoulder"),
            ("Arm", "arm"),
            ("ForeArm", "elbow"),
            ("Hand", "wrist"),
        ):
            body[side + canonical] = f"{side} {joint}"
    vrm = body | {f"{side}HandIndex{k}": f"IndexFinger{k}_{side[0]}" for side in ("Left", "Right") for k in (1, 2)}
    mapping = map_joints(sk, vrm=vrm)
    assert {c: sk.names[j] for c, j in mapping.joints.items() if c in body} == body
    assert {mapping.method[c] for c in body} == {"vrm"}
    expected = {}
    for side in ("Left", "Right"):
        for k in (1, 2, 3):
            expected[f"{side}HandThumb{k}"] = f"Thumb{k - 1}_{side[0]}"
            expected[f"{side}HandIndex{k}"] = f"IndexFinger{k}_{side[0]}"
    assert {e: sk.names[j] for e, j in mapping.extras.items()} == expected
    assert mapping.extra_method["LeftHandIndex1"] == "vrm" and mapping.extra_method["LeftHandThumb1"] == "name"
    assert any("VRM humanoid map has no" in w and "LeftHandIndex3" in w for w in mapping.warnings)
    assert map_joints(sk, {"LeftUpLeg": "Left leg"}, vrm=vrm).method["LeftUpLeg"] == "override"  # the user's wins


def _ik_layout_glb(path: Path) -> Path:
    """A Quaternius-style rig: Root -> Body -> (Spine -> Head, UpperLeg.L -> LowerLeg.L), and Foot.L and the pole
    target PT.L parented to Root; the skin weights Body..Head, the leg and Foot.L (not Root, not PT.L)."""
    import numpy as np

    from tests.core.gltf_builders import USHORT, Builder, trs_matrix, tube_around

    b = Builder()
    root = b.node("Root", parent=b.node("CharacterArmature"))
    body = b.node("Body", parent=root, translation=(0, 1.0, 0))
    spine = b.node("Spine", parent=body, translation=(0, 0.2, 0))
    head = b.node("Head", parent=spine, translation=(0, 0.5, 0))
    thigh = b.node("UpperLeg.L", parent=body, translation=(0.1, 0, 0))
    shin = b.node("LowerLeg.L", parent=thigh, translation=(0, -0.45, 0))
    foot = b.node("Foot.L", parent=root, translation=(0.1, 0.12, 0))
    pole = b.node("PT.L", parent=root, translation=(0.1, 0.5, 0.5))
    joints = [root, body, spine, head, thigh, shin, foot, pole]
    world = {root: (0, 0, 0), body: (0, 1, 0), spine: (0, 1.2, 0), head: (0, 1.7, 0), thigh: (0.1, 1, 0),
             shin: (0.1, 0.55, 0), foot: (0.1, 0.12, 0), pole: (0.1, 0.5, 0.5)}  # fmt: skip
    ibm = np.stack([np.linalg.inv(trs_matrix(world[j])) for j in joints])
    prims = []
    for chain in ([head, spine, body], [thigh, shin, foot]):
        tube = tube_around(np.array([world[j] for j in chain], dtype=float), 0.08)
        skin_index = np.array([joints.index(j) for j in chain])[tube.joints[:, :2]]
        attrs = {"POSITION": b.accessor(tube.positions.astype(np.float32)),
                 "JOINTS_0": b.accessor(np.c_[skin_index, np.zeros((len(tube.joints), 2), int)], USHORT, kind="VEC4"),
                 "WEIGHTS_0": b.accessor(tube.weights.astype(np.float32), kind="VEC4")}  # fmt: skip
        prims.append({"attributes": attrs, "indices": b.accessor(tube.faces.reshape(-1).astype(np.uint32), 5125)})
    b.node("Witch_Body", mesh=b.mesh(prims), skin=b.skin(joints, ibm))
    return b.save_glb(path)


def test_ik_layout_feet_are_attached_below_their_shins(tmp_path: Path) -> None:
    contents = read_gltf(_ik_layout_glb(tmp_path / "ik.glb"))
    c = contents.character
    assert c is not None
    sk = c.skeleton
    parent = {n: sk.names[p] if p >= 0 else None for n, p in zip(sk.names, sk.parents, strict=True)}
    assert parent["Foot.L"] == "LowerLeg.L" and parent["PT.L"] == "Root"  # the unweighted pole target stays
    assert any("'Foot.L' hangs beside the body" in n for n in contents.notes)
    pos = sk.rest_global()[1]
    assert torch.allclose(pos[sk.index("Foot.L")], torch.tensor([0.1, 0.12, 0.0]), atol=1e-5)
    dominant = c.skin_joints.gather(1, c.skin_weights.argmax(1, keepdim=True))[:, 0]
    low = c.vertices[:, 1] < 0.13  # the tube's last ring, at the ankle
    assert {sk.names[j] for j in dominant[low].tolist()} == {"Foot.L"}
    assert {m.name for m in c.meshes} == {"Witch_Body"}


def test_cleric_staff_stays_above_the_floor(tmp_path: Path) -> None:
    """The Cleric's staff, on a joint of its own under the fist, hangs below the floor on the copy of a walk's
    turn (its hand at the hip); the default job turns it at the grip: the result's staff is above the floor on
    every frame, and only its joint is keyed besides the driven ones (props stage, docs/meshes.md)."""
    from retarget_core.refine.props import find_props

    lc = load_character(rig_path(CLERIC.file))
    staff = find_props(lc.character, lc.mapping)
    assert [lc.character.skeleton.names[p.joint] for p in staff] == ["Weapon.R"]
    options = RetargetOptions(frame_start=140, frame_end=240, fps=30.0)
    outputs = run_job(JobInputs(SAMPLES / "motions" / "01_01_first600.bvh", rig_path(CLERIC.file), options=options), tmp_path)
    to_cm = 180.0 / lc.character.height
    lowest = {}
    for name, glb in (("before", outputs.before_glb), ("after", outputs.result_glb)):
        motion = read_gltf(glb).motions[0]
        grot, gpos = motion.global_transforms()
        lowest[name] = lc.character.pose_rows(staff[0].vertices, grot, gpos)[..., 1].min(dim=-1).values * to_cm
    assert float(lowest["before"].min()) < -5.0
    assert float(lowest["after"].min()) >= -0.5  # ACCEPTANCE.md: ground penetration at most 0.5 cm
    report = json.loads(outputs.metrics_json.read_text())["context"]["stage_reports"]["props"]
    assert report["props"] == ["Weapon.R"] and report["frames_changed"] > 0
