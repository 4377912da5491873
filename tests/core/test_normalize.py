"""Normalisation: units, up axis, rest pose, facing and ground are measured, not assumed."""

from __future__ import annotations

from pathlib import Path

import torch

from retarget_core import rotations as rot
from retarget_core.character import Character
from retarget_core.io.bvh import read_bvh
from retarget_core.loading import load_character, load_motion
from retarget_core.mapping import map_joints
from retarget_core.motion import Motion
from retarget_core.normalize import normalize_character, normalize_motion, transform_roots


def test_cc_base_bvh_gets_a_standing_rest_pose_in_metres(samples: Path) -> None:
    lm = load_motion(samples / "motions" / "007_03.bvh")
    assert lm.normalization.unit == "cm"
    assert lm.normalization.rest_pose == "frame"
    _, rest = lm.motion.skeleton.rest_global()
    m = lm.mapping.joints
    assert 1.4 < float(rest[m["Head"], 1]) < 1.9
    assert float(rest[m["LeftFoot"], 1]) < 0.15
    assert float(rest[m["LeftArm"], 0]) > float(rest[m["RightArm"], 0])  # left is +X: faces +Z


def test_cmu_units_and_file_rest_pose(samples: Path) -> None:
    lm = load_motion(samples / "motions" / "01_01_first600.bvh")
    assert lm.normalization.unit == "cmu"
    assert lm.normalization.rest_pose == "file"
    _, pos = lm.motion.global_transforms()
    feet = pos[:, [lm.mapping.joints["LeftToeBase"], lm.mapping.joints["RightToeBase"]], 1].min(-1).values
    assert abs(float(feet.quantile(0.05))) < 0.03  # ground at y = 0


def test_z_up_motion_is_detected_and_undone(samples: Path) -> None:
    raw = read_bvh(samples / "motions" / "01_01_first600.bvh")
    mapping = map_joints(raw.skeleton)
    to_z_up = rot.from_euler("X", torch.tensor([90.0]))
    rotations = raw.rotations.clone()
    translations = raw.translations.clone()
    rotations[:, 0] = rot.mul(to_z_up, rotations[:, 0])
    translations[:, 0] = rot.apply(to_z_up, translations[:, 0])
    z_up = Motion(transform_roots(raw.skeleton, to_z_up, torch.zeros(3)), raw.fps, rotations, translations)
    a, ra = normalize_motion(raw, mapping)
    b, rb = normalize_motion(z_up, mapping)
    assert ra.up_axis == "+Y" and rb.up_axis == "+Z"
    _, pa = a.global_transforms()
    _, pb = b.global_transforms()
    assert (pa - pb).abs().max() < 1e-3


def test_character_in_cm_z_up_facing_back_is_normalised(samples: Path) -> None:
    ref = load_character(samples / "characters" / "mh_female_skinny.glb")
    c = ref.character
    turn = rot.mul(rot.from_euler("Y", torch.tensor([180.0])), rot.from_euler("X", torch.tensor([-90.0])))
    moved = Character(
        c.name, transform_roots(c.skeleton, turn, torch.tensor([3.0, 1.0, 2.0]), 100.0),
        rot.apply(turn, c.vertices * 100.0) + torch.tensor([3.0, 1.0, 2.0]), c.faces, c.skin_joints, c.skin_weights,
    )  # fmt: skip
    back, report = normalize_character(moved, ref.mapping)
    assert report.unit == "cm" and report.up_axis == "+Z"
    assert (back.vertices - c.vertices).abs().max() < 1e-3
    assert abs(back.vertices[:, 1].min()) < 1e-5

