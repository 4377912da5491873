"""The "before" copy stands on the floor for a 3ds Max Biped source at 120 fps (issue 22, item 5).

The case the judge found floating: a clip sent as an animated GLB on the average MakeHuman body, its joints
named and linked as a 3ds Max Biped (``Bip01`` root, ``Bip01 Pelvis``, thighs under ``Bip01 Spine`` kept on the
pelvis by per-frame translations, clavicles under ``Bip01 Neck``, nubs), at 120 fps. Built here from the shipped
samples: CMU 01_01 (forward jumps, 120 fps) copied onto ``builtin:male_average``, placed by its lowest foot
vertex (a plain copy's placement), rebuilt as a Biped and written. "Before" is judged as ACCEPTANCE.md does:
the source file's planted feet at 30 fps, the float of the lowest foot vertex on them.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.copy_retarget import copy_retarget
from retarget_core.io.gltf_write import write_glb
from retarget_core.jobs import JobInputs
from retarget_core.loading import load_character, load_motion
from retarget_core.metrics.acceptance import load_judged_file
from retarget_core.metrics.feet_acceptance import feet_figures, lowest_foot_heights, planted_feet
from retarget_core.motion import Motion
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import prepare
from retarget_core.placement import stand_on_own_feet
from retarget_core.resample import resample
from retarget_core.skeleton import Skeleton

SAMPLES = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples"
CLIP = SAMPLES / "motions" / "01_01_first600.bvh"  # CMU 01_01, forward jumps, 120 fps
WINDOW = (120, 240)  # 1 s at 120 fps between forward jumps
TARGETS = ("mh_male_bulky", "mh_female_skinny")
FLOAT_RANGE_CM = (-0.5, 1.0)  # ACCEPTANCE.md
JUDGE_FPS = 30.0

# Biped joint: (MakeHuman joint it follows, Biped parent); None: the root, which follows the hips.
SIDES = (("Left", "L"), ("Right", "R"))
BIPED: dict[str, tuple[str, str | None]] = {
    "Bip01": ("Hips", None), "Bip01 Pelvis": ("Hips", "Bip01"), "Bip01 Spine": ("Spine", "Bip01 Pelvis"),
    **{k: v for side, s in SIDES for k, v in {
        f"Bip01 {s} Thigh": (f"{side}UpLeg", "Bip01 Spine"), f"Bip01 {s} Calf": (f"{side}Leg", f"Bip01 {s} Thigh"),
        f"Bip01 {s} Foot": (f"{side}Foot", f"Bip01 {s} Calf"), f"Bip01 {s} Toe0": (f"{side}ToeBase", f"Bip01 {s} Foot"),
        f"Bip01 {s} Toe0Nub": (f"{side}ToeBase", f"Bip01 {s} Toe0"),
    }.items()},
    "Bip01 Spine1": ("Spine1", "Bip01 Spine"), "Bip01 Spine2": ("Spine2", "Bip01 Spine1"),
    "Bip01 Neck": ("Neck", "Bip01 Spine2"), "Bip01 Head": ("Head", "Bip01 Neck"),
    "Bip01 HeadNub": ("Head", "Bip01 Head"),
    **{k: v for side, s in SIDES for k, v in {
        f"Bip01 {s} Clavicle": (f"{side}Shoulder", "Bip01 Neck"),
        f"Bip01 {s} UpperArm": (f"{side}Arm", f"Bip01 {s} Clavicle"),
        f"Bip01 {s} Forearm": (f"{side}ForeArm", f"Bip01 {s} UpperArm"),
        f"Bip01 {s} Hand": (f"{side}Hand", f"Bip01 {s} Forearm"),
    }.items()},
}  # fmt: skip
NUB_OFFSET = {"Toe0Nub": (0.0, 0.0, 0.06), "HeadNub": (0.0, 0.18, 0.0)}  # world offset at rest (m)


def _biped_world(ch: Character, grot: Tensor, gpos: Tensor) -> tuple[Tensor, Tensor]:
    """World rotations ``(F, B, 4)`` and positions ``(F, B, 3)`` of the Biped joints from the MakeHuman joints'
    ``(F, J, 4)``, ``(F, J, 3)``: each follows its joint, a nub sits at a fixed offset from it."""
    rest_rot, _ = ch.skeleton.rest_global()
    wr, wp = [], []
    for name, (follow, _) in BIPED.items():
        j = ch.skeleton.index(follow)
        off = next((torch.tensor(o) for k, o in NUB_OFFSET.items() if name.endswith(k)), torch.zeros(3))
        local = rot.apply(rot.inv(rest_rot[j]), off).expand_as(gpos[:, j])
        wr.append(grot[:, j])
        wp.append(gpos[:, j] + rot.apply(grot[:, j], local))
    return torch.stack(wr, 1), torch.stack(wp, 1)


def _locals(parents: list[int], wr: Tensor, wp: Tensor) -> tuple[Tensor, Tensor]:
    """Local rotations and translations ``(F, B, ...)`` reproducing world ``wr``, ``wp`` under ``parents``."""
    lr, lt = wr.clone(), wp.clone()
    for j, p in enumerate(parents):
        if p >= 0:
            lr[:, j] = rot.normalize(rot.mul(rot.inv(wr[:, p]), wr[:, j]))
            lt[:, j] = rot.apply(rot.inv(wr[:, p]), wp[:, j] - wp[:, p])
    return lr, lt


def as_biped(ch: Character, motion: Motion) -> tuple[Character, Motion]:
    """``ch`` and ``motion`` (22 Mixamo-named joints) rebuilt as a 3ds Max Biped: same mesh and skinning, every
    joint where it was in every frame (the thighs' and clavicles' translations animated, as Biped exports are)."""
    names = list(BIPED)
    parents = [names.index(p) if p is not None else -1 for _, p in BIPED.values()]
    rest_r, rest_t = _locals(parents, *_biped_world(ch, *(x[None] for x in ch.skeleton.rest_global())))
    skeleton = Skeleton(names, parents, rest_t[0], rest_r[0])
    skinned = {follow: names.index(n) for n, (follow, _) in BIPED.items() if n != "Bip01" and not n.endswith("Nub")}
    skin = torch.tensor([skinned[n] for n in ch.skeleton.names])[ch.skin_joints]
    body = Character(ch.name, skeleton, ch.vertices, ch.faces, skin, ch.skin_weights, ch.uvs, ch.material)
    lr, lt = _locals(parents, *_biped_world(ch, *motion.global_transforms()))
    return body, Motion(skeleton, motion.fps, lr, lt, motion.name)


def on_lowest_foot_vertex(ch: Character, mapping: JointMapping, motion: Motion) -> Motion:
    """``motion`` raised or lowered so that its lowest foot vertex over the clip is at y = 0 (a plain copy's
    placement: the file stands roughly, not by its planted feet)."""
    low = float(lowest_foot_heights(ch, mapping, motion).min())
    t = motion.translations.clone()
    t[:, 0, 1] -= low
    return replace(motion, translations=t)


@pytest.fixture(scope="module")
def biped_glb(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The clip's window on the average body, as a Biped, written at 120 fps."""
    src = load_motion(CLIP)
    assert src.motion.fps == 120.0
    body = load_character("builtin:male_average")
    copy = copy_retarget(src.motion.slice(*WINDOW), src.mapping, body.character.skeleton, body.mapping)
    copy = on_lowest_foot_vertex(body.character, body.mapping, copy)
    character, motion = as_biped(body.character, copy)
    path = tmp_path_factory.mktemp("biped") / "01_01_biped.glb"
    write_glb(character, motion, path, clip_name="01_01")
    return path


def judged_source_planted(path: Path) -> Tensor:
    """``(F30, 2)`` the judge's planted feet of the source file, in its own coordinates at 30 fps."""
    character, mapping, motion = load_judged_file(path)
    return planted_feet(character, mapping, resample(motion, JUDGE_FPS))


def test_the_file_is_a_biped_at_120_fps(biped_glb: Path) -> None:
    character, mapping, motion = load_judged_file(biped_glb)
    assert motion.fps == pytest.approx(120.0, abs=0.01)
    assert mapping.joints["Hips"] == character.skeleton.index("Bip01 Pelvis")
    assert character.skeleton.parents[mapping.joints["LeftUpLeg"]] == character.skeleton.index("Bip01 Spine")
    assert bool(judged_source_planted(biped_glb).any()), "the judge must see planted feet in the source"


def test_copy_keeps_a_biped_legs_on_its_pelvis(biped_glb: Path) -> None:
    """Copied onto its own skeleton, the Biped's feet are where the file has them (up to one height): the thighs
    follow the pelvis, not the spine they hang under."""
    loaded = load_motion(biped_glb)
    assert loaded.source_character is not None
    body = loaded.source_character
    view = copy_retarget(loaded.motion, loaded.mapping, body.character.skeleton, body.mapping)
    _, gpos_file = loaded.motion.global_transforms()
    _, gpos_view = view.global_transforms()
    for name in ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase"):
        j = body.mapping.joints[name]
        d = gpos_view[:, j] - gpos_file[:, j]
        d[:, 1] -= d[:, 1].mean()
        assert float(d.norm(dim=-1).max()) < 1e-3, name


@pytest.mark.parametrize("dy", [0.08, -0.05])
def test_standing_does_not_depend_on_the_height_it_came_with(biped_glb: Path, dy: float) -> None:
    """A source stands on its own feet at the same height whether it came 8 cm up or 5 cm down."""
    loaded = load_motion(biped_glb)
    assert loaded.source_character is not None
    ch, mapping = loaded.source_character.character, loaded.source_character.mapping
    view = copy_retarget(loaded.motion, loaded.mapping, ch.skeleton, mapping)
    root = ch.skeleton.parents.index(-1)
    moved = replace(view, translations=view.translations.clone())
    moved.translations[:, root, 1] += dy
    a, b = stand_on_own_feet(ch, mapping, view), stand_on_own_feet(ch, mapping, moved)
    assert float((a.translations[:, root, 1] - b.translations[:, root, 1]).abs().max()) < 1e-3


@pytest.mark.parametrize("target", TARGETS)
def test_before_stands_on_the_floor(biped_glb: Path, target: str) -> None:
    prepared = prepare(JobInputs(biped_glb, SAMPLES / "characters" / f"{target}.glb", None, RetargetOptions()))
    assert prepared.before.fps == pytest.approx(120.0, abs=0.01)
    source_planted = judged_source_planted(biped_glb)
    ch, mapping = prepared.target.character, prepared.target.mapping
    figures = feet_figures(ch, mapping, resample(prepared.before, JUDGE_FPS), source_planted)
    assert figures.float_cm is not None
    assert FLOAT_RANGE_CM[0] <= figures.float_cm <= FLOAT_RANGE_CM[1], figures.as_dict()
