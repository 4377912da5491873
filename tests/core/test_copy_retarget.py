"""The copy baseline: bone directions follow the source, rest poses are aligned, feet touch the ground."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.canonical import JointMapping
from retarget_core.copy_retarget import copy_retarget
from retarget_core.loading import LoadedCharacter, LoadedMotion, load_character, load_motion
from retarget_core.motion import Motion

LIMB_BONES = [
    ("LeftArm", "LeftForeArm"), ("LeftForeArm", "LeftHand"), ("RightArm", "RightForeArm"), ("RightForeArm", "RightHand"),
    ("LeftUpLeg", "LeftLeg"), ("LeftLeg", "LeftFoot"), ("RightUpLeg", "RightLeg"), ("RightLeg", "RightFoot"),
    ("LeftShoulder", "LeftArm"), ("RightShoulder", "RightArm"),
]  # fmt: skip
FOOT_BONES = [("LeftFoot", "LeftToeBase"), ("RightFoot", "RightToeBase")]
END_EFFECTORS = ["LeftHand", "RightHand", "LeftFoot", "RightFoot", "Head"]


def _directions(positions: torch.Tensor, mapping: JointMapping, a: str, b: str) -> torch.Tensor:
    v = positions[..., mapping.joints[b], :] - positions[..., mapping.joints[a], :]
    return v / v.norm(dim=-1, keepdim=True)


def _angle_deg(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.acos((u * v).sum(-1).clamp(-1, 1)))


@pytest.fixture(scope="module")
def bulky(samples: Path) -> LoadedCharacter:
    return load_character(samples / "characters" / "mh_male_bulky.glb")


@pytest.fixture(scope="module")
def cc_walk(samples: Path) -> LoadedMotion:
    return load_motion(samples / "motions" / "007_03.bvh")


@pytest.fixture(scope="module")
def mb_clip(samples: Path) -> LoadedMotion:
    return load_motion(samples / "motions" / "01_01_first600.bvh")


@pytest.mark.parametrize("clip", ["cc_walk", "mb_clip"])
def test_limb_directions_follow_the_source(request: pytest.FixtureRequest, clip: str, bulky: LoadedCharacter) -> None:
    src: LoadedMotion = request.getfixturevalue(clip)
    out = copy_retarget(src.motion, src.mapping, bulky.character.skeleton, bulky.mapping)
    assert out.num_frames == src.motion.num_frames and out.fps == src.motion.fps
    _, sp = src.motion.global_transforms()
    _, tp = out.global_transforms()
    for a, b in LIMB_BONES:
        if a in src.mapping.joints and a in bulky.mapping.joints:
            err = _angle_deg(_directions(sp, src.mapping, a, b), _directions(tp, bulky.mapping, a, b))
            assert err.max() < 1.0, f"{a}->{b} deviates by up to {err.max():.2f} degrees"


def _slope_deg(d: torch.Tensor) -> torch.Tensor:
    """Angle ``(...)`` of directions ``d (..., 3)`` below the horizontal."""
    return torch.rad2deg(torch.atan2(-d[..., 1], d[..., [0, 2]].norm(dim=-1)))


@pytest.mark.parametrize("clip", ["cc_walk", "mb_clip"])
def test_feet_turn_as_the_source_feet_do(request: pytest.FixtureRequest, clip: str, bulky: LoadedCharacter) -> None:
    # Feet are aligned on the floor: the target's foot keeps its own rest slope and turns with the source's, so
    # the angle between the two posed foot bones is the (constant) angle between the rest bones once turned
    # to the same heading; a flat source foot gives a flat target foot.
    src: LoadedMotion = request.getfixturevalue(clip)
    out = copy_retarget(src.motion, src.mapping, bulky.character.skeleton, bulky.mapping)
    _, sp = src.motion.global_transforms()
    _, tp = out.global_transforms()
    _, s_rest = src.motion.skeleton.rest_global()
    _, t_rest = bulky.character.skeleton.rest_global()
    for a, b in FOOT_BONES:
        rest_gap = (_slope_deg(_directions(s_rest, src.mapping, a, b)) - _slope_deg(_directions(t_rest, bulky.mapping, a, b))).abs()
        err = _angle_deg(_directions(sp, src.mapping, a, b), _directions(tp, bulky.mapping, a, b))
        assert float((err - rest_gap).abs().max()) < 0.5, (a, float(rest_gap), float(err.min()), float(err.max()))
    # The rest poses themselves: a source standing still in its rest pose leaves the target's feet at rest.
    still = Motion(src.motion.skeleton, src.motion.fps, src.motion.skeleton.rest_rotations[None].repeat(2, 1, 1),
                   src.motion.skeleton.rest_translations[None].repeat(2, 1, 1), "rest")  # fmt: skip
    posed = copy_retarget(still, src.mapping, bulky.character.skeleton, bulky.mapping)
    _, pp = posed.global_transforms()
    for a, b in FOOT_BONES:
        slope = _slope_deg(_directions(pp, bulky.mapping, a, b))
        assert torch.allclose(slope, _slope_deg(_directions(t_rest, bulky.mapping, a, b)), atol=0.1), a


def test_tpose_source_drives_apose_target_into_tpose(mb_clip: LoadedMotion, bulky: LoadedCharacter) -> None:
    """The CMU MotionBuilder rest pose is a T-pose; the MakeHuman target's is an A-pose. A source standing in
    its rest pose must put the target's arms horizontal, and end effectors must point where the source's do."""
    sk = mb_clip.motion.skeleton
    frames = 3
    still = Motion(sk, 30.0, sk.rest_rotations.expand(frames, -1, -1).clone(), sk.rest_translations.expand(frames, -1, -1).clone())
    out = copy_retarget(still, mb_clip.mapping, bulky.character.skeleton, bulky.mapping)
    _, tp = out.global_transforms()
    _, sp = still.global_transforms()
    m = bulky.mapping
    for side in ("Left", "Right"):
        arm = _directions(tp, m, f"{side}Arm", f"{side}Hand")
        assert arm[:, 1].abs().max() < 0.05, f"{side} arm is not horizontal: {arm[0]}"
    for eff in END_EFFECTORS:
        err = _angle_deg(_directions(sp, mb_clip.mapping, "Hips", eff), _directions(tp, m, "Hips", eff))
        # Proportions differ (shoulder height over arm span), so hips-relative directions agree only roughly.
        assert err.max() < 20.0, f"Hips->{eff} differs by {err.max():.1f} degrees on a T-pose source"
    # The A-pose target at rest really had its arms down: the test is not vacuous.
    _, rest = bulky.character.skeleton.rest_global()
    assert _directions(rest, m, "LeftArm", "LeftHand")[1] < -0.3


def test_apose_source_drives_tpose_target(bulky: LoadedCharacter, mb_clip: LoadedMotion) -> None:
    """The reverse: the A-pose MakeHuman skeleton standing still drives the T-pose CMU skeleton into an A-pose."""
    sk = bulky.character.skeleton
    still = Motion(sk, 30.0, sk.rest_rotations.expand(2, -1, -1).clone(), sk.rest_translations.expand(2, -1, -1).clone())
    out = copy_retarget(still, bulky.mapping, mb_clip.motion.skeleton, mb_clip.mapping)
    _, tp = out.global_transforms()
    _, sp = still.global_transforms()
    for a, b in [("LeftArm", "LeftForeArm"), ("RightArm", "RightForeArm"), ("LeftUpLeg", "LeftLeg")]:
        err = _angle_deg(_directions(sp, bulky.mapping, a, b), _directions(tp, mb_clip.mapping, a, b))
        assert err.max() < 1.0


def test_feet_touch_the_ground(cc_walk: LoadedMotion, bulky: LoadedCharacter) -> None:
    out = copy_retarget(cc_walk.motion, cc_walk.mapping, bulky.character.skeleton, bulky.mapping)
    verts = bulky.character.pose_vertices(*out.global_transforms())
    lowest = verts[..., 1].min(dim=-1).values
    # Walking: a foot is on the floor in the first second (the clip's own floor rises later: it is kept).
    assert lowest[:60].abs().median() < 0.015, f"feet are {lowest[:60].median():.3f} m off the ground at the start"
    assert lowest[:60].min() > -0.03


def test_root_motion_scaled_by_leg_length(cc_walk: LoadedMotion, bulky: LoadedCharacter) -> None:
    from retarget_core.normalize import leg_length

    out = copy_retarget(cc_walk.motion, cc_walk.mapping, bulky.character.skeleton, bulky.mapping)
    _, sp = cc_walk.motion.global_transforms()
    _, tp = out.global_transforms()
    hs, ht = sp[:, cc_walk.mapping.joints["Hips"]], tp[:, bulky.mapping.joints["Hips"]]
    ratio = leg_length(bulky.character.skeleton, bulky.mapping) / leg_length(cc_walk.motion.skeleton, cc_walk.mapping)
    travelled_s = (hs[-1] - hs[1])[[0, 2]].norm()
    travelled_t = (ht[-1] - ht[1])[[0, 2]].norm()
    assert travelled_s > 0.5
    assert abs(float(travelled_t / travelled_s) - ratio) < 0.01
    in_place = copy_retarget(cc_walk.motion, cc_walk.mapping, bulky.character.skeleton, bulky.mapping, in_place=True)
    _, ip = in_place.global_transforms()
    assert ip[:, bulky.mapping.joints["Hips"]][:, [0, 2]].abs().max() < 1e-4


def test_heading_follows_the_source(cc_walk: LoadedMotion, bulky: LoadedCharacter) -> None:
    out = copy_retarget(cc_walk.motion, cc_walk.mapping, bulky.character.skeleton, bulky.mapping)
    s_rot, _ = cc_walk.motion.global_transforms()
    t_rot, _ = out.global_transforms()
    s_rest, _ = cc_walk.motion.skeleton.rest_global()
    t_rest, _ = bulky.character.skeleton.rest_global()
    sh, th = cc_walk.mapping.joints["Hips"], bulky.mapping.joints["Hips"]
    fwd = torch.tensor([0.0, 0.0, 1.0])
    s_fwd = rot.apply(rot.mul(s_rot[:, sh], rot.inv(s_rest[sh])), fwd)
    t_fwd = rot.apply(rot.mul(t_rot[:, th], rot.inv(t_rest[th])), fwd)
    assert _angle_deg(s_fwd, t_fwd).max() < 10.0
