"""Forward kinematics and skinning of a subset of vertices in rotation-matrix form, for the collision stage's
inner loop (a few small batched matrix products per joint instead of quaternion algebra; the same result as
:mod:`retarget_core.kinematics` up to float rounding)."""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch
from torch import Tensor

from retarget_core.character import Character
from retarget_core.geometry.skin_rows import skin_rows
from retarget_core.kinematics import SKINNING_CHUNK_BYTES, dense_weights


def rotvec_to_matrix(r: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (Rodrigues; smooth at zero:
    ``(1 - cos t) / t^2`` is written ``sinc(t / 2)^2 / 2``)."""
    theta = (r.pow(2).sum(-1, keepdim=True) + 1e-12).sqrt()[..., None]  # (..., 1, 1)
    zero = torch.zeros_like(r[..., 0])
    k = torch.stack([zero, -r[..., 2], r[..., 1], r[..., 2], zero, -r[..., 0], -r[..., 1], r[..., 0], zero], dim=-1)
    k = k.reshape(*r.shape[:-1], 3, 3)
    half = 0.5 * theta
    a = torch.sin(theta) / theta
    b = 0.5 * (torch.sin(half) / half).pow(2)
    eye = torch.eye(3, dtype=r.dtype).expand_as(k)
    return eye + a * k + b * (k @ k)


class PointPoser:
    """Poses ``points (P,)`` of ``character`` from local rotation matrices; ``seg_joints (S,)`` the joints
    whose skinning transforms are returned as segment transforms."""

    def __init__(self, character: Character, points: Tensor, seg_joints: list[int]) -> None:
        sk = character.skeleton
        self.parents = sk.parents
        rest_rot, rest_pos = sk.rest_global()
        self.rest_rot_t = roma.unitquat_to_rotmat(rest_rot.float()).transpose(-1, -2)  # (J, 3, 3)
        self.rest_pos = rest_pos.float()
        self.points = points
        self.rest = character.vertices.float().index_select(0, points)  # (P, 3)
        self.seg_joints = torch.tensor(seg_joints, dtype=torch.long)
        self.skin_joints = character.skin_joints.index_select(0, points)  # (P, K) sparse influences
        weights = character.skin_weights.index_select(0, points)
        self.skin_weights = weights.float()  # (P, K)
        self.weights = dense_weights(self.skin_joints, weights, sk.num_joints).float()  # (P, J): the points' rows only

    def __call__(self, local_rot: Tensor, local_trans: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """From local rotation matrices ``(F, J, 3, 3)`` and translations ``(F, J, 3)``: posed points
        ``(F, P, 3)``, segment transforms ``(F, S, 3, 4)`` (rest world -> posed world), joint positions ``(F, J, 3)``."""
        mats, gpos = self.transforms(local_rot, local_trans)
        return self.skin(mats), mats.index_select(1, self.seg_joints), gpos

    def skin(self, mats: Tensor) -> Tensor:
        """Posed points ``(F, P, 3)`` from skinning transforms ``(F, J, 3, 4)``; without gradients, a chunk of
        frames at a time (each frame's figures are the same: only the memory they take at once differs)."""
        if torch.is_grad_enabled() and mats.requires_grad:
            return self._skin(mats)
        step = max(1, SKINNING_CHUNK_BYTES // max(1, 24 * mats.element_size() * len(self.points)))
        out = mats.new_empty(mats.shape[0], len(self.points), 3)
        for s in range(0, mats.shape[0], step):
            out[s : s + step] = self._skin(mats[s : s + step])
        return out

    def _skin(self, mats: Tensor) -> Tensor:
        """:meth:`skin` of all frames ``mats (F, J, 3, 4)`` at once (their blended transforms held together)."""
        f_n, j_n = mats.shape[:2]
        blended = torch.matmul(self.weights, mats.reshape(f_n, j_n, 12)).reshape(f_n, -1, 3, 4)  # (F, P, 3, 4)
        return (blended[..., :3] * self.rest[None, :, None, :]).sum(-1) + blended[..., 3]

    def transforms(self, local_rot: Tensor, local_trans: Tensor) -> tuple[Tensor, Tensor]:
        """Skinning transforms ``(F, J, 3, 4)`` (rest world -> posed world) and joint positions ``(F, J, 3)`` from
        local rotation matrices ``(F, J, 3, 3)`` and translations ``(F, J, 3)``."""
        g_rot: list[Tensor] = []
        g_pos: list[Tensor] = []
        for j, p in enumerate(self.parents):
            if p < 0:
                g_rot.append(local_rot[:, j])
                g_pos.append(local_trans[:, j])
            else:
                g_rot.append(g_rot[p] @ local_rot[:, j])
                g_pos.append(g_pos[p] + (g_rot[p] @ local_trans[:, j, :, None])[..., 0])
        grot = torch.stack(g_rot, dim=1)  # (F, J, 3, 3)
        gpos = torch.stack(g_pos, dim=1)  # (F, J, 3)
        r = grot @ self.rest_rot_t  # (F, J, 3, 3)
        t = gpos - (r @ self.rest_pos[..., None])[..., 0]
        return torch.cat([r, t[..., None]], dim=-1), gpos

    def plan(self, frames: Tensor, points: Tensor, num_joints: int) -> RowPlan:
        """What :meth:`pose_rows` needs to pose the (frame, point) rows ``frames (N,)``, ``points (N,)`` (indices
        into the frames posed and :attr:`points`) from transforms of ``num_joints`` joints."""
        joints = self.skin_joints.index_select(0, points)  # (N, K)
        mat_rows = (frames[:, None] * num_joints + joints).reshape(-1)
        return RowPlan(mat_rows, self.skin_weights.index_select(0, points), self.rest.index_select(0, points))


@dataclass
class RowPlan:
    """Rows of posed points: ``mat_rows (N*K,)`` rows of the flattened transforms ``(F*J, 12)`` of each row's
    influences, their weights ``(N, K)`` and the rows' rest positions ``(N, 3)``."""

    mat_rows: Tensor
    weight: Tensor
    rest: Tensor


def pose_rows(plan: RowPlan, mats: Tensor) -> Tensor:
    """Posed positions ``(N, 3)`` of the rows of ``plan`` from skinning transforms ``mats (F, J, 3, 4)``: only the
    rows an energy reads are posed, each from its own influences (compiled on the CPU, :func:`skin_rows`)."""
    n, k = plan.weight.shape
    if mats.device.type == "cpu":
        return skin_rows(plan.mat_rows.reshape(n, k), plan.weight, plan.rest, mats.reshape(-1, 3, 4))
    m = mats.reshape(-1, 12).index_select(0, plan.mat_rows).reshape(n, k, 12)
    blended = torch.bmm(plan.weight[:, None, :], m).reshape(n, 3, 4)
    return torch.bmm(blended[..., :3], plan.rest[..., None])[..., 0] + blended[..., 3]


__all__ = ["PointPoser", "RowPlan", "pose_rows", "rotvec_to_matrix"]
