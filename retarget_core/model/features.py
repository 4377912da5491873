"""Inputs and outputs of the recurrent retargeter, on the 22 canonical joints so that any rig works.

Source motion features, per frame ``(F, SOURCE_DIM)``, facing-invariant (expressed in the hips' heading frame):
- the copy baseline's world rotation of each canonical joint relative to its rest, ``H^-1 Q(t) Q_rest^-1``, in
  6D (first two matrix columns) (22 x 6): the source's rotations as the copy put them on the target;
- the source's canonical joint positions relative to its hips, on the source body, divided by its height
  (22 x 3): where the hands are relative to the source's own body (what contacts depend on);
- the copy's root velocity (heading frame, per frame, / target height) (3), root height / target height (1),
  and the heading's turn rate (1).
Target code, per body ``(TARGET_DIM,)``: the rest canonical joint positions relative to the hips / height
(22 x 3), per-segment girths (mean and max distance of the segment's dominant vertices from its bone line, /
height, 22 x 2) and the height / 1.80 m (1). Girths need only the skin weights and rest vertices, so they work
for any mesh topology and cost milliseconds. Optionally (``NetworkConfig.geometry = "pointnet"``, the paper's
choice) the network replaces the girths by a PointNet code over the rig's geometry points ``(POINTS, POINT_DIM)``:
a fixed, seeded subsample of rest vertices, each its position relative to the hips / height (3) and its skin
weight summed per canonical joint (22) (:func:`geometry_points`).

Outputs: a residual rotation per canonical joint in 6D (zero = identity), applied in the joint's rest world
frame on top of the copy's local rotation, and a root offset (heading frame, in heights) added to the copy's
root; the root-velocity term of the energy keeps its changes smooth. (Not the paper's integrated velocity
residual: it drifts over a clip, docs/model-recurrent.md.) A zero output gives the copy exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.body_parts import BodyParts
from retarget_core.canonical import CANONICAL_JOINTS, JointMapping
from retarget_core.copy_retarget import BONE_CHILDREN
from retarget_core.kinematics import forward_kinematics
from retarget_core.skeleton import Skeleton

NUM_CANONICAL = len(CANONICAL_JOINTS)
SOURCE_DIM = NUM_CANONICAL * 6 + NUM_CANONICAL * 3 + 5
TARGET_DIM = NUM_CANONICAL * 3 + NUM_CANONICAL * 2 + 1
GIRTHS = slice(NUM_CANONICAL * 3, NUM_CANONICAL * 5)
"""Where the girths lie in the target code (the PointNet variant reads the code without them)."""
POINTS = 2048
POINT_DIM = 3 + NUM_CANONICAL
POINTS_SEED = 0
REFERENCE_HEIGHT_M = 1.80
IDENTITY_6D = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])


def canonical_indices(mapping: JointMapping) -> Tensor:
    """Skeleton joint of each canonical joint ``(22,)``, -1 where the rig lacks it."""
    return torch.tensor([mapping.joints.get(c, -1) for c in CANONICAL_JOINTS], dtype=torch.long)


def root_joint(skeleton: Skeleton, mapping: JointMapping) -> int:
    """The world root above the hips (the joint whose translation carries the root motion)."""
    hips = mapping.joints["Hips"]
    chain = [hips, *skeleton.ancestors(hips)]
    return chain[-1]


def heading(positions: Tensor, mapping: JointMapping) -> Tensor:
    """Yaw-only rotations ``(..., 4)`` of the body's facing from world joint positions ``(..., J, 3)``: the
    body's left axis (hips and shoulders, horizontal) taken to +X, so the rest pose (facing +Z) is identity."""
    m = mapping.joints
    left = positions[..., m["LeftUpLeg"], :] - positions[..., m["RightUpLeg"], :]
    left = left + positions[..., m["LeftArm"], :] - positions[..., m["RightArm"], :]
    yaw = torch.atan2(-left[..., 2], left[..., 0])
    half = 0.5 * yaw
    zero = torch.zeros_like(half)
    return torch.stack([zero, torch.sin(half), zero, torch.cos(half)], dim=-1)


def to_6d(q: Tensor) -> Tensor:
    """First two columns ``(..., 6)`` of the rotation matrices of unit quaternions ``(..., 4)``."""
    m = rot.to_matrix(q)
    return torch.cat([m[..., :, 0], m[..., :, 1]], dim=-1)


def from_6d(x: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` from 6D rotations ``(..., 6)`` (Gram-Schmidt; differentiable)."""
    a, b = x[..., :3], x[..., 3:]
    c0 = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    b = b - (c0 * b).sum(-1, keepdim=True) * c0
    c1 = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    c2 = torch.cross(c0, c1, dim=-1)
    return roma.rotmat_to_unitquat(torch.stack([c0, c1, c2], dim=-1))


@dataclass
class TargetRig:
    """What the network needs of one target body: its canonical joints, rest frames and code.

    joints: ``(22,)`` skeleton index per canonical joint (-1 missing); rest_world_rot: ``(J, 4)``;
    code: ``(TARGET_DIM,)``; height (m); root: the joint carrying root motion; points: ``(POINTS, POINT_DIM)``
    the geometry points of :func:`geometry_points`."""

    skeleton: Skeleton
    mapping: JointMapping
    joints: Tensor
    rest_world_rot: Tensor
    rest_world_pos: Tensor
    code: Tensor
    height: float
    root: int
    points: Tensor


def segment_girths(rest_pos: Tensor, vertices: Tensor, parts: BodyParts, mapping: JointMapping, height: float) -> Tensor:
    """Per canonical segment ``(22, 2)``: mean and max distance of its dominant vertices from the bone line
    (joint toward its canonical child, or its parent's direction for hands, head and toes), / height."""
    out = torch.zeros(NUM_CANONICAL, 2)
    for s, name in enumerate(parts.names):
        c = CANONICAL_JOINTS.index(name)
        verts = vertices[parts.vertex_part == s]
        if len(verts) < 3:
            continue
        p = rest_pos[parts.joints[s]]
        child = next((k for k in BONE_CHILDREN.get(name, ()) if k in mapping.joints), None)
        axis = rest_pos[mapping.joints[child]] - p if child is not None else verts.mean(0) - p
        axis = axis / axis.norm().clamp_min(1e-6)
        rel = verts - p
        radial = (rel - (rel @ axis)[:, None] * axis).norm(dim=-1)
        out[c, 0], out[c, 1] = radial.mean() / height, radial.max() / height
    return out


def point_sample(num_vertices: int, count: int = POINTS, seed: int = POINTS_SEED) -> Tensor:
    """``count`` vertex indices ``(count,)``: a seeded random subset, every vertex repeated in turn to fill up
    when the mesh has fewer (a max pool is blind to repeats)."""
    order = torch.randperm(num_vertices, generator=torch.Generator().manual_seed(seed))
    return order.repeat(-(-count // num_vertices))[:count]


def geometry_points(rest_pos: Tensor, vertices: Tensor, parts: BodyParts, mapping: JointMapping, height: float) -> Tensor:
    """PointNet input ``(POINTS, POINT_DIM)``: sampled rest vertices ``(V, 3)`` relative to the hips / height,
    and each one's skin weight per canonical joint (the segment weights of ``parts``; 0 for unmapped ones)."""
    idx = point_sample(vertices.shape[0])
    hips = rest_pos[mapping.joints["Hips"]]
    weights = torch.zeros(len(idx), NUM_CANONICAL)
    cols = torch.tensor([CANONICAL_JOINTS.index(n) for n in parts.names], dtype=torch.long)
    weights[:, cols] = parts.weights[idx].float()
    return torch.cat([(vertices[idx].float() - hips) / height, weights], dim=-1)


def target_rig(skeleton: Skeleton, mapping: JointMapping, vertices: Tensor, parts: BodyParts) -> TargetRig:
    """The :class:`TargetRig` of a body (rest ``vertices (V, 3)`` in the skeleton's rest pose)."""
    rest_rot, rest_pos = skeleton.rest_global()
    height = float(vertices[:, 1].max() - vertices[:, 1].min())
    joints = canonical_indices(mapping)
    hips = rest_pos[mapping.joints["Hips"]]
    offsets = torch.zeros(NUM_CANONICAL, 3)
    ok = joints >= 0
    offsets[ok] = (rest_pos[joints[ok]] - hips) / height
    girths = segment_girths(rest_pos, vertices.float(), parts, mapping, height)
    code = torch.cat([offsets.reshape(-1), girths.reshape(-1), torch.tensor([height / REFERENCE_HEIGHT_M])])
    points = geometry_points(rest_pos.float(), vertices, parts, mapping, height)
    return TargetRig(skeleton, mapping, joints, rest_rot, rest_pos, code.float(), height, root_joint(skeleton, mapping), points)


def source_features(
    rig: TargetRig,
    copy_rot: Tensor,
    copy_trans: Tensor,
    source_canonical_pos: Tensor,
    source_height: float | Tensor,
) -> tuple[Tensor, Tensor]:
    """Features ``(B, F, SOURCE_DIM)`` and the copy's heading ``(B, F, 4)``.

    copy_rot, copy_trans: ``(B, F, J, 4)``, ``(B, F, J, 3)`` the copy baseline on the target rig;
    source_canonical_pos: ``(B, F, 22, 3)`` the source's canonical joint positions on its own body (zeros where
    missing); source_height: the source body's height (m), a float or ``(B, 1, 1, 1)``."""
    grot, gpos = forward_kinematics(rig.skeleton.parents, copy_rot, copy_trans)
    head = heading(gpos, rig.mapping)
    inv_head = rot.inv(head)
    ok = rig.joints >= 0
    idx = rig.joints.clamp_min(0)
    rel = rot.mul(grot[..., idx, :], rot.inv(rig.rest_world_rot[idx]))
    rel = rot.mul(inv_head[..., None, :], rel)
    rot6 = to_6d(rel) * ok[:, None].to(rel.dtype)
    hips = source_canonical_pos[..., :1, :]
    src = rot.apply(inv_head[..., None, :], source_canonical_pos - hips) / source_height
    root = gpos[..., rig.mapping.joints["Hips"], :]
    vel = torch.cat([torch.zeros_like(root[..., :1, :]), root[..., 1:, :] - root[..., :-1, :]], dim=-2)
    vel = rot.apply(inv_head, vel) / rig.height
    turn = rot.mul(inv_head[..., :-1, :], head[..., 1:, :])
    turn_rate = torch.cat([torch.zeros_like(turn[..., :1, 1]), 2.0 * turn[..., 1]], dim=-1)
    feats = torch.cat(
        [rot6.flatten(-2), src.flatten(-2), vel, root[..., 1:2] / rig.height, turn_rate[..., None]], dim=-1
    )
    return feats, head


def apply_residual(
    rig: TargetRig, copy_rot: Tensor, copy_trans: Tensor, head: Tensor, rot6: Tensor, root_offset: Tensor
) -> tuple[Tensor, Tensor]:
    """Local rotations ``(B, F, J, 4)`` and translations ``(B, F, J, 3)``: the copy with the network's residual
    rotations ``rot6 (B, F, 22, 6)`` (zero = identity, in each joint's rest world frame) and root velocity
    offset ``root_offset (B, F, 3)`` (heading frame, in heights). An offset, not an integrated velocity: a
    velocity residual trained on 60-frame windows drifts by decimetres over a long clip."""
    ok = rig.joints >= 0
    idx = rig.joints[ok]
    delta = from_6d(rot6[..., ok, :] + IDENTITY_6D.to(rot6.dtype))  # (B, F, K, 4)
    rw = rig.rest_world_rot[idx]
    delta_local = rot.mul(rot.mul(rot.inv(rw), delta), rw)
    new_rot = copy_rot.clone()
    new_rot[..., idx, :] = rot.mul(copy_rot[..., idx, :], delta_local)
    offset = rot.apply(head, root_offset) * rig.height
    new_trans = copy_trans.clone()
    new_trans[..., rig.root, :] = copy_trans[..., rig.root, :] + offset
    return new_rot, new_trans


def source_canonical_positions(skeleton: Skeleton, mapping: JointMapping, rotations: Tensor, translations: Tensor) -> Tensor:
    """World positions ``(F, 22, 3)`` of the canonical joints of a motion (zeros where the rig lacks one)."""
    _, gpos = forward_kinematics(skeleton.parents, rotations, translations)
    idx = canonical_indices(mapping)
    out = gpos[:, idx.clamp_min(0)]
    return out * (idx >= 0)[:, None].to(out.dtype)


__all__ = [
    "GIRTHS",
    "IDENTITY_6D",
    "NUM_CANONICAL",
    "POINTS",
    "POINT_DIM",
    "SOURCE_DIM",
    "TARGET_DIM",
    "TargetRig",
    "apply_residual",
    "canonical_indices",
    "from_6d",
    "geometry_points",
    "heading",
    "point_sample",
    "root_joint",
    "segment_girths",
    "source_canonical_positions",
    "source_features",
    "target_rig",
    "to_6d",
]
