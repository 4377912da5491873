"""Batched, differentiable forward kinematics and linear blend skinning (torch).

Follows the glTF definition: a joint's world transform is its parent's world transform times its local
``T * R`` (no scale; scale is baked into offsets on reading), and a skinned vertex is
``sum_k w_k * world_k * inverse_bind_k * v`` with ``inverse_bind_k`` the inverse of the rest world transform.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import torch
from torch import Tensor

from retarget_core import rotations as rot

SKINNING_CHUNK_BYTES = 48 * 2**20  # a chunk's blended matrices (float32): about 64 frames of a 15k-vertex body


def forward_kinematics(
    parents: Sequence[int], local_rotations: Tensor, local_translations: Tensor
) -> tuple[Tensor, Tensor]:
    """World rotations ``(..., J, 4)`` and positions ``(..., J, 3)`` from local rotations ``(..., J, 4)`` and
    local translations ``(..., J, 3)`` (roots: world). ``parents[j] < j``; ``-1`` marks a root.

    One step per depth of the hierarchy (all joints of a depth at once), not per joint: the same products on
    the same values as joint after joint, so bit-identical, and differentiable."""
    batch = torch.broadcast_shapes(local_rotations.shape[:-2], local_translations.shape[:-2])
    local_rotations = local_rotations.expand(*batch, *local_rotations.shape[-2:])
    local_translations = local_translations.expand(*batch, *local_translations.shape[-2:])
    grot, gpos = local_rotations.clone(), local_translations.clone()  # roots are their own world transform
    for joints, joint_parents in depth_levels(tuple(int(p) for p in parents), local_rotations.device):
        parent_rot = grot.index_select(-2, joint_parents)
        moved = gpos.index_select(-2, joint_parents) + rot.apply(parent_rot, local_translations.index_select(-2, joints))
        grot = grot.index_copy(-2, joints, rot.mul(parent_rot, local_rotations.index_select(-2, joints)))
        gpos = gpos.index_copy(-2, joints, moved)
    return grot, gpos


@lru_cache(maxsize=256)
def depth_levels(parents: tuple[int, ...], device: torch.device) -> tuple[tuple[Tensor, Tensor], ...]:
    """Per depth below the roots: the joints ``(n,)`` at that depth and their parents ``(n,)``."""
    depth: list[int] = []
    for p in parents:
        depth.append(0 if p < 0 else depth[p] + 1)
    levels = []
    for d in range(1, max(depth, default=0) + 1):
        joints = [j for j, dj in enumerate(depth) if dj == d]
        levels.append((torch.tensor(joints, device=device), torch.tensor([parents[j] for j in joints], device=device)))
    return tuple(levels)


def global_to_local(
    parents: Sequence[int], global_rotations: Tensor, global_positions: Tensor
) -> tuple[Tensor, Tensor]:
    """Local rotations ``(..., J, 4)`` and translations ``(..., J, 3)`` from world ones (inverse of FK)."""
    local_r = global_rotations.clone()
    local_t = global_positions.clone()
    for j, p in enumerate(parents):
        if p >= 0:
            inv_p = rot.inv(global_rotations[..., p, :])
            local_r[..., j, :] = rot.mul(inv_p, global_rotations[..., j, :])
            local_t[..., j, :] = rot.apply(inv_p, global_positions[..., j, :] - global_positions[..., p, :])
    return rot.normalize(local_r), local_t


def skinning_matrices(
    rest_rotations: Tensor, rest_positions: Tensor, posed_rotations: Tensor, posed_positions: Tensor
) -> Tensor:
    """Per-joint 3x4 matrices ``(..., J, 3, 4)`` taking rest-pose world points to posed world points:
    ``posed * rest^-1``. Rest ``(J, 4)``, ``(J, 3)``; posed ``(..., J, 4)``, ``(..., J, 3)``."""
    delta_rot = rot.mul(posed_rotations, rot.inv(rest_rotations))
    r = rot.to_matrix(delta_rot)
    t = posed_positions - (r @ rest_positions.unsqueeze(-1)).squeeze(-1)
    return torch.cat([r, t.unsqueeze(-1)], dim=-1)


def dense_weights(joint_indices: Tensor, joint_weights: Tensor, num_joints: int) -> Tensor:
    """Dense skinning weights ``(V, J)`` from per-vertex influences ``(V, K)`` indices and weights."""
    w = torch.zeros(joint_indices.shape[0], num_joints, dtype=joint_weights.dtype)
    w.scatter_add_(1, joint_indices.long(), joint_weights)
    return w


def linear_blend_skinning(rest_vertices: Tensor, weights: Tensor, matrices: Tensor,
                          frame_chunk: int | None = None) -> Tensor:  # fmt: skip
    """Posed vertices ``(..., V, 3)`` from rest vertices ``(V, 3)``, dense weights ``(V, J)`` and per-joint
    matrices ``(..., J, 3, 4)`` (from :func:`skinning_matrices`). Frames are processed in chunks to bound memory
    (default: as many as keep a chunk's blended matrices within :data:`SKINNING_CHUNK_BYTES`)."""
    batch = matrices.shape[:-3]
    flat = matrices.reshape(-1, matrices.shape[-3], 12)
    homo = torch.cat([rest_vertices, torch.ones_like(rest_vertices[:, :1])], dim=-1)  # (V, 4)
    v_n = rest_vertices.shape[0]
    step = frame_chunk or max(1, SKINNING_CHUNK_BYTES // max(1, 12 * flat.element_size() * v_n))
    out = flat.new_empty(flat.shape[0], v_n, 3)  # filled chunk by chunk: the frames are not held twice
    for start in range(0, flat.shape[0], step):
        blended = torch.matmul(weights, flat[start : start + step])  # (C, V, 12)
        blended = blended.reshape(blended.shape[0], -1, 3, 4)
        out[start : start + step] = (blended @ homo.unsqueeze(-1)).squeeze(-1)
    return out.reshape(*batch, v_n, 3)
