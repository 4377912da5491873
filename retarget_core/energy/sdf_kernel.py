"""One segment grid's blended signed distance at rest-frame points, with its gradient, compiled (numba) on the CPU.

The value of :func:`retarget_core.energy.sdf._sample_grid`'s tensor form (trilinear in the two channels, paper 2's
blend, ``+ |x - clamp(x)|`` outside the box; computed in float64, so equal to float32 rounding) in one pass per
point instead of a dozen tensor operations, and its gradient in the point from the same pass (the tensor form's
backward was most of the collision solver's step). Grids need at least two voxels along each axis.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True, inline="always")
def _axis(x: float, lo: float, voxel: float, n: int) -> tuple[int, float, float, float]:
    """Along one axis: the lower voxel ``i``, the fraction ``t`` toward ``i + 1``, ``d t / d x`` (0 where the
    point is clamped) and the distance outside the box (signed: ``x - clamp(x)``)."""
    hi = lo + (n - 1) * voxel
    inside = min(max(x, lo), hi)
    u = (inside - lo) / voxel
    i = min(max(int(math.floor(u)), 0), n - 2)
    return i, u - i, (1.0 / voxel if lo < x < hi else 0.0), x - inside


@numba.njit(cache=True, nogil=True, inline="always")
def _trilinear(grid: np.ndarray, c: int, i: int, j: int, k: int, tx: float, ty: float,
               tz: float) -> tuple[float, float, float, float]:  # fmt: skip
    """Channel ``c`` of ``grid (2, Nz, Ny, Nx)`` in the cell at ``(z, y, x) = (k, j, i)``, fractions ``t``: the
    value and its derivatives in ``tx, ty, tz``."""
    c00 = grid[c, k, j, i] + tx * (grid[c, k, j, i + 1] - grid[c, k, j, i])
    c01 = grid[c, k, j + 1, i] + tx * (grid[c, k, j + 1, i + 1] - grid[c, k, j + 1, i])
    c10 = grid[c, k + 1, j, i] + tx * (grid[c, k + 1, j, i + 1] - grid[c, k + 1, j, i])
    c11 = grid[c, k + 1, j + 1, i] + tx * (grid[c, k + 1, j + 1, i + 1] - grid[c, k + 1, j + 1, i])
    e0, e1 = c00 + ty * (c01 - c00), c10 + ty * (c11 - c10)
    dx0 = (grid[c, k, j, i + 1] - grid[c, k, j, i]) * (1 - ty) + (grid[c, k, j + 1, i + 1] - grid[c, k, j + 1, i]) * ty
    dx1 = (grid[c, k + 1, j, i + 1] - grid[c, k + 1, j, i]) * (1 - ty) + (
        grid[c, k + 1, j + 1, i + 1] - grid[c, k + 1, j + 1, i]) * ty  # fmt: skip
    return e0 + tz * (e1 - e0), dx0 + tz * (dx1 - dx0), (c01 - c00) * (1 - tz) + (c11 - c10) * tz, e1 - e0


@numba.njit(cache=True, nogil=True)
def _sample(grid: np.ndarray, lo: np.ndarray, voxel: float, blend: float, pts: np.ndarray, out: np.ndarray,
            grad: np.ndarray, want_grad: bool) -> None:  # fmt: skip
    """``out (N,)`` blended signed distances of ``pts (N, 3)`` in ``grid (2, Nz, Ny, Nx)`` (voxel (0, 0, 0) at
    ``lo (3,)``); ``grad (N, 3)`` their gradients when ``want_grad``."""
    nz, ny, nx = grid.shape[1], grid.shape[2], grid.shape[3]
    for n in range(pts.shape[0]):
        i, tx, sx, ox = _axis(pts[n, 0], lo[0], voxel, nx)
        j, ty, sy, oy = _axis(pts[n, 1], lo[1], voxel, ny)
        k, tz, sz, oz = _axis(pts[n, 2], lo[2], voxel, nz)
        seg, sgx, sgy, sgz = _trilinear(grid, 0, i, j, k, tx, ty, tz)
        char, cgx, cgy, cgz = _trilinear(grid, 1, i, j, k, tx, ty, tz)
        p = min(max(seg / blend, 0.0), 1.0)
        outside = math.sqrt(ox * ox + oy * oy + oz * oz)
        out[n] = p * seg + (1.0 - p) * char + outside
        if want_grad:
            a = p + ((seg - char) / blend if 0.0 < seg < blend else 0.0)  # d out / d seg
            b = 1.0 - p  # d out / d char
            inv = 1.0 / outside if outside > 0.0 else 0.0
            grad[n, 0] = (a * sgx + b * cgx) * sx + ox * inv
            grad[n, 1] = (a * sgy + b * cgy) * sy + oy * inv
            grad[n, 2] = (a * sgz + b * cgz) * sz + oz * inv


class _SampleGrid(torch.autograd.Function):
    """:func:`_sample` with the gradient it computed in the same pass as the backward (CPU tensors)."""

    @staticmethod
    def forward(ctx: Any, pts: Tensor, grid: np.ndarray, lo: np.ndarray, voxel: float, blend: float) -> Tensor:
        want = ctx.needs_input_grad[0]
        x = pts.detach().double().contiguous().numpy()
        out = np.empty(len(x))
        grad = np.empty((len(x) if want else 0, 3))
        _sample(grid, lo, voxel, blend, x, out, grad, want)
        if want:
            ctx.save_for_backward(torch.from_numpy(grad).to(pts.dtype))
        return torch.from_numpy(out).to(pts.dtype)

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor, None, None, None, None]:
        (grad,) = ctx.saved_tensors
        return g[:, None] * grad, None, None, None, None


def sample_grid(grid: Tensor, lo: Tensor, voxel: float, blend: float, pts: Tensor) -> Tensor:
    """Blended signed distance ``(N,)`` (``pts``' dtype) of rest-frame points ``pts (N, 3)`` (CPU) in one
    segment's ``grid (2, Nz, Ny, Nx)`` (voxel (0, 0, 0) at ``lo (3,)``, edge ``voxel``, blend width ``blend``);
    differentiable in the points."""
    g = grid.detach().numpy()
    return _SampleGrid.apply(pts, g, lo.detach().double().numpy(), float(voxel), float(blend))


__all__ = ["sample_grid"]
