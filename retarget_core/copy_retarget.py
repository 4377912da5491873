"""The copy baseline: per-joint rotation transfer with rest alignment, root motion scaled by leg length.

For every canonical joint ``c`` mapped on both skeletons, the target's world rotation follows the source's
world rotation change since its rest pose, after aligning the two rest poses bone by bone:

    Q_t(t) = Q_s(t) * Q_s_rest^-1 * A_c * Q_t_rest,   with   A_c * d_t = d_s

where ``d_s``/``d_t`` are the rest directions of the bone (joint to its canonical child) of source and target.
``A_c`` is the shortest arc between them (a T-pose source drives an A-pose target correctly); the hips and
spine use full frames (bone direction plus the body's left axis) so their twist is aligned too. The feet are
aligned on the floor instead: both rest poses stand flat on it, so ``A_c`` turns only about the vertical, taking
the horizontal part of ``d_t`` to that of ``d_s``. A flat source foot then stays flat on the target whatever the
slope of each rig's ankle-to-toe bone (the shortest arc would tilt a foot whose ankle sits higher over a shorter
foot toes-up by the difference of the slopes: 4 degrees, a toe joint 1 cm up, from an average to a heavy body).
Mapped fingers and toes (``mapping.extras``) follow the same formula, each aligned by the previous segment's (or the
hand's) alignment followed by the shortest arc of its bone; twist bones take their share of their limb's twist
(:mod:`retarget_core.extras`). Every other joint of the target keeps its rest local rotation. This is what a production rotation retargeter
(Unreal IK Retargeter's FK chains, Mixamo) gives without IK: the "before" of every comparison.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from retarget_core import extras
from retarget_core import rotations as rot
from retarget_core.canonical import CANONICAL_JOINTS, CANONICAL_PARENT, JointMapping
from retarget_core.kinematics import forward_kinematics
from retarget_core.motion import Motion
from retarget_core.normalize import foot_clearance, foot_joint_indices, left_axis, leg_length
from retarget_core.skeleton import Skeleton

# Canonical joints whose alignment uses a full frame: primary = bone direction, secondary = body's left.
FRAME_ALIGNED = ("Hips", "Spine", "Spine1", "Spine2", "Neck")
# The bone direction of a canonical joint points to the first mapped joint of this list.
BONE_CHILDREN: dict[str, tuple[str, ...]] = {
    "Hips": ("Spine", "Spine1", "Spine2", "Neck"),
    "Spine": ("Spine1", "Spine2", "Neck"),
    "Spine1": ("Spine2", "Neck"),
    "Spine2": ("Neck", "Head"),
    "Neck": ("Head",),
    "LeftShoulder": ("LeftArm",),
    "LeftArm": ("LeftForeArm",),
    "LeftForeArm": ("LeftHand",),
    "RightShoulder": ("RightArm",),
    "RightArm": ("RightForeArm",),
    "RightForeArm": ("RightHand",),
    "LeftUpLeg": ("LeftLeg",),
    "LeftLeg": ("LeftFoot",),
    "LeftFoot": ("LeftToeBase",),
    "RightUpLeg": ("RightLeg",),
    "RightLeg": ("RightFoot",),
    "RightFoot": ("RightToeBase",),
}
# Canonical joints aligned on the floor (about the vertical only; see module doc), when both rest bones are
# closer to horizontal than FLOOR_ALIGNED_MAX_SLOPE_DEG (a rig whose rest foot points down falls back to the arc).
FLOOR_ALIGNED = ("LeftFoot", "RightFoot")
FLOOR_ALIGNED_MAX_SLOPE_DEG = 60.0
CONTACT_FRAME_CLEARANCE_M = 0.03
MIN_BONE_LENGTH_M = 1e-3


def _bone_direction(name: str, positions: Tensor, mapping: JointMapping) -> Tensor | None:
    """Rest direction ``(3,)`` of canonical joint ``name`` toward its first mapped canonical child that is not
    at the same place (some rigs stack joints, e.g. CMU's Hips and LowerBack)."""
    for child in BONE_CHILDREN.get(name, ()):
        if child in mapping.joints:
            d = positions[mapping.joints[child]] - positions[mapping.joints[name]]
            if float(d.norm()) > MIN_BONE_LENGTH_M:
                return d
    return None


def _floor_alignment(dt: Tensor, ds: Tensor) -> Tensor | None:
    """The rotation ``(4,)`` about the vertical taking the horizontal part of ``dt (3,)`` to that of ``ds (3,)``;
    None when either bone is steeper than :data:`FLOOR_ALIGNED_MAX_SLOPE_DEG`."""
    min_cos = math.cos(math.radians(FLOOR_ALIGNED_MAX_SLOPE_DEG))
    flat = []
    for d in (dt, ds):
        h = d.clone()
        h[1] = 0.0
        if float(h.norm()) < min_cos * float(d.norm()):
            return None
        flat.append(h)
    return rot.between(flat[0], flat[1])


def rest_alignment(
    source: Skeleton, source_map: JointMapping, target: Skeleton, target_map: JointMapping
) -> dict[str, Tensor]:
    """Per canonical joint mapped on both sides, the world rotation ``A (4,)`` with ``A * d_target = d_source``
    (the feet: their horizontal parts; see module doc).

    Joints without a bone direction on both sides (hands, head, toes) inherit their canonical parent's."""
    _, spos = source.rest_global()
    _, tpos = target.rest_global()
    s_left, t_left = left_axis(spos, source_map), left_axis(tpos, target_map)
    align: dict[str, Tensor] = {}
    for name in CANONICAL_JOINTS:
        if name not in source_map.joints or name not in target_map.joints:
            continue
        ds, dt = _bone_direction(name, spos, source_map), _bone_direction(name, tpos, target_map)
        if ds is not None and dt is not None:
            if name in FRAME_ALIGNED:
                fs = rot.from_frame(ds, s_left, primary_axis=1, secondary_axis=0)
                ft = rot.from_frame(dt, t_left, primary_axis=1, secondary_axis=0)
                align[name] = rot.normalize(rot.mul(fs, rot.inv(ft)))
            elif name in FLOOR_ALIGNED and (on_floor := _floor_alignment(dt, ds)) is not None:
                align[name] = on_floor
            else:
                align[name] = rot.between(dt, ds)
        else:
            parent = CANONICAL_PARENT[name]
            while parent is not None and parent not in align:
                parent = CANONICAL_PARENT[parent]
            align[name] = align[parent] if parent is not None else rot.identity()
    return align


def _hips_offset_from_root(target: Skeleton, hips: int, local_r: Tensor, local_t: Tensor) -> Tensor:
    """World position ``(F, 3)`` of the hips joint when every root sits at the origin."""
    zero_t = local_t.clone()
    for j, p in enumerate(target.parents):
        if p < 0:
            zero_t[:, j] = 0.0
    _, pos = forward_kinematics(target.parents, local_r, zero_t)
    return pos[:, hips]


def _follow_canonical_parents(target: Skeleton, target_map: JointMapping, local_r: Tensor, local_t: Tensor) -> None:
    """In place on ``local_t (F, J, 3)``: a mapped joint that hangs under another mapped joint than its canonical
    parent (a 3ds Max Biped's thighs under ``Bip01 Spine``, its clavicles under ``Bip01 Neck``) keeps its rest
    offset from the canonical parent, as the rig itself does with per-frame translations (the spine bends without
    carrying the legs); its rest local translation would swing the legs with the spine."""
    mapped = set(target_map.joints.values())
    rest_rot, rest_pos = target.rest_global()
    for name, j in target_map.joints.items():
        cp = target_map.joints.get(CANONICAL_PARENT.get(name) or "", -1)
        ancestors = target.ancestors(j)
        nearest = next((a for a in ancestors if a in mapped), None)
        if cp < 0 or cp not in ancestors or nearest == cp:
            continue
        w_rot, w_pos = forward_kinematics(target.parents, local_r, local_t)
        p = target.parents[j]
        turn = rot.mul(w_rot[:, cp], rot.inv(rest_rot[cp]))  # (F, 4) the canonical parent's turn since rest
        offset = rot.apply(turn, (rest_pos[j] - rest_pos[cp]).expand_as(w_pos[:, j]))
        local_t[:, j] = rot.apply(rot.inv(w_rot[:, p]), w_pos[:, cp] + offset - w_pos[:, p])


def copy_retarget(
    source: Motion,
    source_map: JointMapping,
    target: Skeleton,
    target_map: JointMapping,
    *,
    in_place: bool = False,
) -> Motion:
    """The source motion performed by the target skeleton by rotation copying (see module doc).

    Both inputs must be normalised (metres, Y up, rest facing +Z, ground at y = 0; the target's rest pose
    standing on y = 0). Root motion is the source hips trajectory scaled by the ratio of leg lengths; the
    height is then shifted so the feet touch the ground when the source's feet do.
    Returns a motion on ``target`` with ``(F, J_target, 4)`` rotations and ``(F, J_target, 3)`` translations.
    """
    frames = source.num_frames
    s_rot, s_pos = source.global_transforms()
    s_rest_rot, _ = source.skeleton.rest_global()
    t_rest_rot, t_rest_pos = target.rest_global()
    align = rest_alignment(source.skeleton, source_map, target, target_map)

    desired: dict[int, Tensor] = {}
    for name, a in align.items():
        sj, tj = source_map.joints[name], target_map.joints[name]
        delta = rot.mul(s_rot[:, sj], rot.inv(s_rest_rot[sj]))
        desired[tj] = rot.normalize(rot.mul(rot.mul(delta, a), t_rest_rot[tj]))
    twists: dict[int, extras.TwistDriver] = {}
    if target_map.extras:  # fingers and toes as the body (rest-aligned), twist bones from their limbs
        aligned = extras.digit_alignment(source.skeleton, source_map, target, target_map, align)
        desired.update(extras.digit_world_rotations(s_rot, s_rest_rot, t_rest_rot, aligned))
        twists = extras.twist_drivers(target, target_map)

    local_r = target.rest_rotations.unsqueeze(0).repeat(frames, 1, 1)
    local_t = target.rest_translations.unsqueeze(0).repeat(frames, 1, 1)
    world: list[Tensor] = []
    for j, p in enumerate(target.parents):
        parent_world = world[p] if p >= 0 else rot.identity(frames)
        if j in twists:
            desired[j] = twists[j].world(world, local_r, desired, target.rest_rotations)
        if j in desired:
            world.append(desired[j])
            local_r[:, j] = rot.normalize(rot.mul(rot.inv(parent_world), desired[j]))
        else:
            world.append(rot.mul(parent_world, local_r[:, j]))

    _follow_canonical_parents(target, target_map, local_r, local_t)

    # Root motion: source hips scaled by leg length ratio, placed through the target's root joint(s).
    scale = leg_length(target, target_map) / max(leg_length(source.skeleton, source_map), 1e-6)
    hips_s = s_pos[:, source_map.joints["Hips"]]
    hips_t = hips_s * scale
    if in_place:
        hips_t = torch.stack([torch.zeros(frames), hips_t[:, 1], torch.zeros(frames)], dim=-1)
    hips_index = target_map.joints["Hips"]
    offset = _hips_offset_from_root(target, hips_index, local_r, local_t)
    root = ([hips_index, *target.ancestors(hips_index)])[-1]
    local_t[:, root] = hips_t - offset

    # Height: feet on the ground wherever the source's feet are (the target's clearance matches the scaled source's).
    _, t_pos = forward_kinematics(target.parents, local_r, local_t)
    _, s_rest_pos = source.skeleton.rest_global()
    s_clear = foot_clearance(s_pos, s_rest_pos, foot_joint_indices(source.skeleton, source_map)) * scale
    t_clear = foot_clearance(t_pos, t_rest_pos, foot_joint_indices(target, target_map))
    grounded = s_clear < CONTACT_FRAME_CLEARANCE_M
    diff = (t_clear - s_clear)[grounded] if bool(grounded.any()) else (t_clear - s_clear)[:1]
    shift = float(diff.median())
    local_t[:, root, 1] -= shift
    return Motion(target, source.fps, local_r, local_t, source.name)
