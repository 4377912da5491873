"""Normalisation of motions and characters: metres, Y up, rest pose facing +Z, ground at y = 0.

Raw readers keep a file's units, axes and rest pose. This module measures them and brings data into the
library's frame. Rest-pose differences are measured here, not assumed away: a motion whose zero pose is not a
standing pose (e.g. the Reallusion CC_Base BVH exports, whose zero pose has every bone pointing up) gets a rest
pose taken from its most upright frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton

UNIT_CANDIDATES: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": 0.0254,
    "cmu": 0.0254 / 0.45,  # CMU ASF/AMC length unit: 1/0.45 inch
    "dm": 0.1,
}
TYPICAL_HEIGHT_M = 1.7
# Standing height over (thigh + shin + hips-to-head chain), measured on MakeHuman bodies (~1.17).
HEIGHT_PER_CHAIN_LENGTH = 1.17


@dataclass
class NormalizationReport:
    """What normalisation found and did, for the user-facing report."""

    unit: str = "m"
    scale: float = 1.0
    up_axis: str = "+Y"
    rest_pose: str = "file"
    rest_frame: int | None = None
    facing_yaw_degrees: float = 0.0
    ground_m: float = 0.0  # the floor height found in the file (metres, Y up), subtracted from the roots
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


def chain_length(skeleton: Skeleton, start: int, end: int) -> float:
    """Sum of bone lengths from joint ``start`` down to its descendant ``end`` (0 when not a descendant)."""
    total = 0.0
    j = end
    while j != start and j >= 0:
        total += float(skeleton.rest_translations[j].norm())
        j = skeleton.parents[j]
    return total if j == start else 0.0


def body_chain_length(skeleton: Skeleton, mapping: JointMapping) -> float:
    """Pose-independent size of a skeleton in its own units: mean leg (UpLeg to Foot) plus Hips to Head."""
    m = mapping.joints
    legs = [chain_length(skeleton, m[f"{s}UpLeg"], m[f"{s}Foot"]) for s in ("Left", "Right")]
    return sum(legs) / 2 + chain_length(skeleton, m["Hips"], m["Head"])


def leg_length(skeleton: Skeleton, mapping: JointMapping) -> float:
    """Mean length of the two legs from hip joint to ankle, in the skeleton's units."""
    m = mapping.joints
    return sum(chain_length(skeleton, m[f"{s}UpLeg"], m[f"{s}Foot"]) for s in ("Left", "Right")) / 2


def guess_unit(skeleton: Skeleton, mapping: JointMapping) -> tuple[str, float]:
    """The unit name and metres-per-unit that make the body's estimated height closest to a typical adult."""
    size = body_chain_length(skeleton, mapping) * HEIGHT_PER_CHAIN_LENGTH
    if size <= 0:
        return "m", 1.0
    best = min(
        UNIT_CANDIDATES.items(), key=lambda kv: abs(torch.log(torch.tensor(size * kv[1] / TYPICAL_HEIGHT_M)).item())
    )
    return best


def _axis_name(v: Tensor) -> str:
    i = int(v.abs().argmax())
    return ("+" if v[i] > 0 else "-") + "XYZ"[i]


def up_rotation(up: Tensor) -> Tensor:
    """The rotation ``(4,)`` that takes the signed axis nearest to ``up (3,)`` onto +Y."""
    i = int(up.abs().argmax())
    axis = torch.zeros(3)
    axis[i] = torch.sign(up[i])
    if i == 1 and up[i] < 0:
        return torch.tensor([1.0, 0.0, 0.0, 0.0])  # 180 degrees about X
    return rot.between(axis, torch.tensor([0.0, 1.0, 0.0]))


def left_axis(positions: Tensor, mapping: JointMapping) -> Tensor:
    """The body's left direction ``(..., 3)`` from hips and shoulders in world positions ``(..., J, 3)``."""
    m = mapping.joints
    hips = positions[..., m["LeftUpLeg"], :] - positions[..., m["RightUpLeg"], :]
    arms = positions[..., m["LeftArm"], :] - positions[..., m["RightArm"], :]
    h = hips / hips.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    a = arms / arms.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return h + a


def facing_yaw(positions: Tensor, mapping: JointMapping) -> Tensor:
    """Heading angle (radians, about +Y) of a Y-up pose ``(J, 3)``: 0 when it faces +Z."""
    left = left_axis(positions, mapping)
    forward = torch.cross(left, torch.tensor([0.0, 1.0, 0.0]), dim=-1)
    return torch.atan2(forward[0], forward[2])


def yaw_quat(angle: Tensor | float) -> Tensor:
    """A rotation ``(4,)`` by ``angle`` radians about +Y."""
    a = torch.as_tensor(angle, dtype=torch.float32) / 2
    return torch.stack([torch.zeros(()), torch.sin(a), torch.zeros(()), torch.cos(a)])


def transform_roots(skeleton: Skeleton, rotation: Tensor, translation: Tensor, scale: float = 1.0) -> Skeleton:
    """The skeleton with every root joint moved by ``x -> rotation * (scale * x) + translation``."""
    rest_t = skeleton.rest_translations * scale
    rest_r = skeleton.rest_rotations.clone()
    for j, p in enumerate(skeleton.parents):
        if p < 0:
            rest_t[j] = rot.apply(rotation, rest_t[j]) + translation
            rest_r[j] = rot.normalize(rot.mul(rotation, rest_r[j]))
    return Skeleton(list(skeleton.names), list(skeleton.parents), rest_t, rest_r)


def _transform_motion_roots(motion: Motion, rotation: Tensor, scale: float) -> tuple[Tensor, Tensor]:
    rotations = motion.rotations.clone()
    translations = motion.translations * scale
    for j, p in enumerate(motion.skeleton.parents):
        if p < 0:
            rotations[:, j] = rot.mul(rotation, rotations[:, j])
            translations[:, j] = rot.apply(rotation, translations[:, j])
    return rotations, translations


def uprightness(global_positions: Tensor, mapping: JointMapping) -> Tensor:
    """Per-pose score ``(...)``, lower is more like standing: legs straight down, spine straight up."""
    m = mapping.joints
    down = torch.tensor([0.0, -1.0, 0.0])
    score = torch.zeros(global_positions.shape[:-2])
    for a, b, d in (
        ("LeftUpLeg", "LeftFoot", down),
        ("RightUpLeg", "RightFoot", down),
        ("LeftUpLeg", "LeftLeg", down),
        ("RightUpLeg", "RightLeg", down),
        ("Hips", "Head", -down),
    ):
        v = global_positions[..., m[b], :] - global_positions[..., m[a], :]
        v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        score = score + (1.0 - (v * d).sum(-1))
    return score


def rest_is_standing(skeleton: Skeleton, mapping: JointMapping, tolerance: float = 0.35) -> bool:
    """Whether the skeleton's rest pose (already Y up) stands: legs down and spine up within ``tolerance``."""
    _, pos = skeleton.rest_global()
    return bool(uprightness(pos, mapping) < tolerance)


def normalize_motion(
    motion: Motion, mapping: JointMapping, unit: str | None = None
) -> tuple[Motion, NormalizationReport]:
    """The motion in metres, Y up, with a standing rest pose that faces +Z, and the ground at y = 0.

    ``unit`` forces a unit (a key of ``UNIT_CANDIDATES``); by default it is guessed from the body's size.
    The clip is rotated as a whole so that its rest pose faces +Z; the clip's own heading over time is kept.
    """
    report = NormalizationReport()
    sk = motion.skeleton
    if unit is None:
        report.unit, report.scale = guess_unit(sk, mapping)
    else:
        if unit not in UNIT_CANDIDATES:
            raise ValueError(f"unknown unit {unit!r}; choose one of {sorted(UNIT_CANDIDATES)}")
        report.unit, report.scale = unit, UNIT_CANDIDATES[unit]

    # Up axis: the mean head-above-feet direction over the clip (pose-robust, unlike a zero pose).
    _, gpos = motion.global_transforms()
    m = mapping.joints
    feet = (gpos[:, m["LeftFoot"]] + gpos[:, m["RightFoot"]]) / 2
    up_vec = (gpos[:, m["Head"]] - feet).mean(0)
    up_q = up_rotation(up_vec)
    report.up_axis = _axis_name(up_vec)
    rotations, translations = _transform_motion_roots(motion, up_q, report.scale)
    skeleton = transform_roots(sk, up_q, torch.zeros(3), report.scale)
    moved = Motion(skeleton, motion.fps, rotations, translations, motion.name)
    grot, gpos = moved.global_transforms()

    # Rest pose: the file's, if it stands; otherwise the most upright frame of the clip, heading removed.
    if rest_is_standing(skeleton, mapping):
        report.rest_pose = "file"
        rest_rot, rest_pos = skeleton.rest_global()
        yaw = facing_yaw(rest_pos, mapping)
        turn = yaw_quat(-yaw)
        report.facing_yaw_degrees = float(torch.rad2deg(-yaw))
        rotations, translations = _transform_motion_roots(moved, turn, 1.0)
        skeleton = transform_roots(skeleton, turn, torch.zeros(3))
        moved = Motion(skeleton, moved.fps, rotations, translations, moved.name)
    else:
        frame = int(uprightness(gpos, mapping).argmin())
        report.rest_pose = "frame"
        report.rest_frame = frame
        report.notes.append(
            f"the file's zero pose is not a standing pose; frame {frame} (the most upright) is used as the rest pose"
        )
        yaw = facing_yaw(gpos[frame], mapping)
        turn = yaw_quat(-yaw)
        rest_local_r = moved.rotations[frame].clone()
        rest_local_t = moved.translations[frame].clone()
        roots = [j for j, p in enumerate(skeleton.parents) if p < 0]
        for j in roots:
            rest_local_r[j] = rot.normalize(rot.mul(turn, rest_local_r[j]))
            rest_local_t[j] = rot.apply(turn, rest_local_t[j])
            rest_local_t[j, 0] = 0.0
            rest_local_t[j, 2] = 0.0
        skeleton = skeleton.with_rest(rest_local_r, rest_local_t)
        moved = Motion(skeleton, moved.fps, moved.rotations, moved.translations, moved.name)

    # Ground: where the feet stand when they are down (a low percentile over the clip).
    ground = estimate_ground(moved, mapping)
    report.ground_m = float(ground)
    translations = moved.translations.clone()
    rest_t = moved.skeleton.rest_translations.clone()
    for j in (j for j, p in enumerate(moved.skeleton.parents) if p < 0):
        translations[:, j, 1] -= ground
    _, rest_pos = moved.skeleton.rest_global()
    rest_floor = float(rest_pos[foot_joint_indices(moved.skeleton, mapping), 1].min())
    for j in (j for j, p in enumerate(moved.skeleton.parents) if p < 0):
        rest_t[j, 1] -= rest_floor
    skeleton = Skeleton(list(moved.skeleton.names), list(moved.skeleton.parents), rest_t, moved.skeleton.rest_rotations)
    return Motion(skeleton, moved.fps, moved.rotations, translations, moved.name), report


def foot_joint_indices(skeleton: Skeleton, mapping: JointMapping) -> list[int]:
    """Foot, toe and every joint below them (end sites included): the joints that touch the floor."""
    roots = [mapping.joints[n] for n in ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase") if n in mapping.joints]
    out = set(roots)
    for j, p in enumerate(skeleton.parents):
        if p in out:
            out.add(j)
    return sorted(out)


def foot_clearance(global_positions: Tensor, rest_positions: Tensor, feet: list[int]) -> Tensor:
    """Per frame ``(F,)``: how far the foot joints are above where they are when standing on y = 0
    (the minimum over ``feet`` of posed height minus rest height). ``rest_positions (J, 3)`` stand on y = 0."""
    return (global_positions[:, feet, 1] - rest_positions[feet, 1]).min(dim=-1).values


def estimate_ground(motion: Motion, mapping: JointMapping, percentile: float = 5.0) -> float:
    """The height of the floor the clip stands on: a low percentile of the per-frame foot clearance."""
    feet = foot_joint_indices(motion.skeleton, mapping)
    _, gpos = motion.global_transforms()
    _, rest_pos = motion.skeleton.rest_global()
    rest_pos = rest_pos - torch.tensor([0.0, float(rest_pos[feet, 1].min()), 0.0])
    clearance = foot_clearance(gpos, rest_pos, feet)
    return float(torch.quantile(clearance, percentile / 100.0))


def normalize_character(
    character: Character, mapping: JointMapping, unit: str | None = None
) -> tuple[Character, NormalizationReport]:
    """The character in metres, Y up, facing +Z, with the lowest vertex on y = 0 and the hips above x = z = 0."""
    report = NormalizationReport()
    sk = character.skeleton
    _, pos = sk.rest_global()
    m = mapping.joints
    if unit is not None:
        report.unit, report.scale = unit, UNIT_CANDIDATES[unit]
    else:
        extent = float((character.vertices.max(0).values - character.vertices.min(0).values).max())
        if not 0.3 <= extent <= 4.0:
            report.unit, report.scale = guess_unit(sk, mapping)
            report.notes.append(f"the body is {extent:.3g} units tall; read as {report.unit}")
    feet = (pos[m["LeftFoot"]] + pos[m["RightFoot"]]) / 2
    up_vec = pos[m["Head"]] - feet
    up_q = up_rotation(up_vec)
    report.up_axis = _axis_name(up_vec)
    pos_up = rot.apply(up_q, pos * report.scale)
    yaw = facing_yaw(pos_up, mapping)
    report.facing_yaw_degrees = float(torch.rad2deg(-yaw))
    turn = rot.mul(yaw_quat(-yaw), up_q)
    verts = rot.apply(turn, character.vertices * report.scale)
    hips = rot.apply(turn, pos[m["Hips"]] * report.scale)
    shift = torch.stack([-hips[0], -verts[:, 1].min(), -hips[2]])
    skeleton = transform_roots(sk, turn, shift, report.scale)
    out = Character(
        character.name, skeleton, verts + shift, character.faces, character.skin_joints, character.skin_weights,
        character.uvs, character.material, character.meshes, character.mesh_of_vertex,
    )  # fmt: skip
    return out, report
