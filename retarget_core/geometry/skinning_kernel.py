"""Linear blend skinning over each vertex's few influences, compiled (numba), for posing without gradients.

The dense form (:func:`retarget_core.kinematics.linear_blend_skinning`) blends every joint's matrix into every
vertex, ``(V, J) @ (J, 12)`` a frame, though a vertex has at most a handful of influences: on a 22-joint body
five times the work, and more on rigs with fingers and twist bones. Here each vertex blends its own ``K``
influences' matrices and applies them, in float64, frame blocks on threads (the kernel releases the GIL).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from retarget_core.geometry.bvh_kernels import run_in_blocks

MIN_VERTEX_FRAMES = 100_000  # posed vertices per thread at least: fewer are not worth a thread's start


@numba.njit(cache=True, nogil=True, inline="always")
def blend_row(mats: np.ndarray, joints: np.ndarray, weights: np.ndarray, rest: np.ndarray, out: np.ndarray) -> None:
    """One vertex: ``out (3,)`` = sum_k weights[k] * mats[joints[k]] @ (rest, 1), zero weights skipped;
    ``mats (T, 3, 4)``, ``joints, weights (K,)``, ``rest (3,)``."""
    x, y, z = rest[0], rest[1], rest[2]
    for r in range(3):
        acc = 0.0
        for k in range(joints.shape[0]):
            w = weights[k]
            if w != 0.0:
                m = mats[joints[k], r]
                acc += w * (m[0] * x + m[1] * y + m[2] * z + m[3])
        out[r] = acc


@numba.njit(cache=True, nogil=True)
def _skin(rest: np.ndarray, joints: np.ndarray, weights: np.ndarray, matrices: np.ndarray, out: np.ndarray) -> None:
    """``out (F, V, 3)``: :func:`blend_row` of every vertex ``rest (V, 3)``, ``joints, weights (V, K)`` on every
    frame of ``matrices (F, J, 3, 4)``."""
    for f in range(matrices.shape[0]):
        for v in range(rest.shape[0]):
            blend_row(matrices[f], joints[v], weights[v], rest[v], out[f, v])


def sparse_skinning(rest: Tensor, joints: Tensor, weights: Tensor, matrices: Tensor) -> Tensor:
    """Posed vertices ``(F, V, 3)`` (``matrices``' dtype) from rest vertices ``(V, 3)``, influences ``joints (V, K)``
    with ``weights (V, K)`` and per-joint matrices ``(F, J, 3, 4)``; no gradient flows."""
    rest_np = rest.detach().to(torch.float64).contiguous().numpy()
    joints_np = joints.detach().to(torch.int64).contiguous().numpy()
    weights_np = weights.detach().to(torch.float64).contiguous().numpy()
    mats = matrices.detach().to(torch.float64).contiguous().numpy()
    out = torch.empty(mats.shape[0], rest_np.shape[0], 3, dtype=matrices.dtype)
    out_np = out.numpy()
    per_thread = max(1, MIN_VERTEX_FRAMES // max(1, len(rest_np)))
    run_in_blocks(lambda b: _skin(rest_np, joints_np, weights_np, mats[b], out_np[b]), len(mats), per_thread)
    return out


__all__ = ["sparse_skinning"]
