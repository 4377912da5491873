"""Posing chosen (frame, point) rows from skinning transforms, with its gradient, compiled (numba) on the CPU.

Each row blends its own few influences' transforms and applies them to its rest position; the gradient adds each
row's ``weight * grad (x) (rest, 1)`` back into its influences' transforms. The differentiable gather-and-blend
form (kept for other devices) spent most of the collision solver's backward scattering every row's padded
influences back into the transforms one small product at a time.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from retarget_core.geometry.skinning_kernel import blend_row


@numba.njit(cache=True, nogil=True)
def _pose(mat_rows: np.ndarray, weight: np.ndarray, rest: np.ndarray, mats: np.ndarray, out: np.ndarray) -> None:
    """``out (N, 3)``: :func:`blend_row` of each row ``n`` (``mat_rows, weight (N, K)``, ``rest (N, 3)``) from
    ``mats (T, 3, 4)``."""
    for n in range(rest.shape[0]):
        blend_row(mats, mat_rows[n], weight[n], rest[n], out[n])


@numba.njit(cache=True, nogil=True)
def _pose_grad(mat_rows: np.ndarray, weight: np.ndarray, rest: np.ndarray, grad: np.ndarray, out: np.ndarray) -> None:
    """``out (T, 3, 4)`` += the gradient of :func:`_pose`'s rows for ``grad (N, 3)``: per row and influence,
    ``weight * grad[n, r] * (rest[n], 1)`` into row ``r`` of its transform."""
    for n in range(rest.shape[0]):
        for k in range(weight.shape[1]):
            w = weight[n, k]
            if w != 0.0:
                t = mat_rows[n, k]
                for r in range(3):
                    g = w * grad[n, r]
                    out[t, r, 0] += g * rest[n, 0]
                    out[t, r, 1] += g * rest[n, 1]
                    out[t, r, 2] += g * rest[n, 2]
                    out[t, r, 3] += g


class _PoseRows(torch.autograd.Function):
    """:func:`_pose` with :func:`_pose_grad` as its backward (CPU tensors)."""

    @staticmethod
    def forward(ctx: Any, mats: Tensor, mat_rows: Tensor, weight: Tensor, rest: Tensor) -> Tensor:
        ctx.save_for_backward(mat_rows, weight, rest)
        ctx.num_mats = mats.shape[0]
        out = mats.new_empty(rest.shape[0], 3)
        _pose(mat_rows.numpy(), weight.numpy(), rest.numpy(), mats.contiguous().numpy(), out.numpy())
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None, None]:
        mat_rows, weight, rest = ctx.saved_tensors
        out = grad.new_zeros(ctx.num_mats, 3, 4)
        _pose_grad(mat_rows.numpy(), weight.numpy(), rest.numpy(), grad.contiguous().numpy(), out.numpy())
        return out, None, None, None


def skin_rows(mat_rows: Tensor, weight: Tensor, rest: Tensor, mats: Tensor) -> Tensor:
    """Posed rows ``(N, 3)`` in ``mats``' dtype from transforms ``mats (T, 3, 4)`` (CPU): row ``n`` blends the
    transforms ``mat_rows[n] (K,)`` with ``weight[n] (K,)`` (zeros skipped) and applies them to ``rest[n] (3,)``.
    Differentiable in ``mats``."""
    dt = mats.dtype
    return _PoseRows.apply(mats, mat_rows.contiguous(), weight.to(dt).contiguous(), rest.to(dt).contiguous())


__all__ = ["skin_rows"]
