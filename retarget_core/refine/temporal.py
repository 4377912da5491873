"""Residuals that are smooth in time by construction: a uniform cubic B-spline over knots every few frames.

A residual ``r(t) = sum_k c_k beta3(t / K - k)`` (``beta3`` the centred cubic B-spline, support [-2, 2]) is C2
in time, so its third difference (jerk) is bounded by the knots' differences over ``K^3``: no per-frame jitter
can appear, whatever the optimiser does to the knots.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def cubic_bspline(x: Tensor) -> Tensor:
    """The centred uniform cubic B-spline ``beta3(x)`` elementwise (support ``|x| < 2``, partition of unity)."""
    a = x.abs()
    inner = 2.0 / 3.0 - a.pow(2) + 0.5 * a.pow(3)
    outer = (2.0 - a).clamp_min(0.0).pow(3) / 6.0
    return torch.where(a < 1.0, inner, outer)


def knot_count(frames: int, spacing: int) -> int:
    """Knots ``k = -1 .. ceil((F - 1) / K) + 1`` cover every frame with a full set of four basis functions."""
    return int(math.ceil(max(frames - 1, 0) / spacing)) + 3


def bspline_basis(frames: int, spacing: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """``(F, N)`` basis matrix: row t holds ``beta3(t / K - k)`` for knots ``k = -1 ..`` (see :func:`knot_count`)."""
    n = knot_count(frames, spacing)
    t = torch.arange(frames, dtype=dtype)[:, None] / spacing
    k = torch.arange(n, dtype=dtype)[None, :] - 1.0
    return cubic_bspline(t - k)


def smoothstep(x: Tensor) -> Tensor:
    """``3x^2 - 2x^3`` on ``x`` clamped to [0, 1] (C1 ramp)."""
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def fallback_weights(cap: Tensor, ramp: int) -> Tensor:
    """``(F,)`` weights in 0..1 that are at most ``cap (F,)`` on every frame and rise smoothly back to 1 over
    ``ramp`` frames around the capped ones: ``w(t) = min_u c_u + (1 - c_u) * smoothstep(|t - u| / ramp)`` over the
    caps ``c`` closed first (a gap of at most ``ramp`` frames between two capped spans takes their higher cap), so a
    span where a change made things worse returns smoothly towards the input, without blips between spans."""
    f_n = cap.shape[0]
    closed = close_caps(cap.float(), ramp)
    idx = torch.nonzero(closed < 1.0).flatten()
    if len(idx) == 0:
        return torch.ones(f_n)
    t = torch.arange(f_n, dtype=torch.float32)
    c = closed[idx][None, :]
    ramped = c + (1.0 - c) * smoothstep((t[:, None] - idx[None, :].float()).abs() / max(ramp, 1))
    return ramped.amin(dim=1)


def close_caps(cap: Tensor, ramp: int) -> Tensor:
    """``(F,)`` caps lowered in the gaps of at most ``ramp`` frames between capped spans (a grey closing of the
    withdrawn share ``1 - cap``: dilation then erosion over ``ramp // 2`` frames each side); never above ``cap``."""
    half = max(ramp // 2, 0)
    if half == 0:
        return cap
    pool = torch.nn.functional.max_pool1d
    withdrawn = (1.0 - cap)[None, None]
    dilated = pool(withdrawn, 2 * half + 1, stride=1, padding=half)
    closed = -pool(-dilated, 2 * half + 1, stride=1, padding=half)
    return torch.minimum(cap, 1.0 - closed[0, 0])




def weighted_smooth(wanted: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """``(F, C)`` the wanted curves ``(F, C)`` smoothed in time by a normalised Gaussian convolution: at each frame
    the ``weight (F,)``-weighted mean of the wanted values around it (standard deviation ``sigma`` frames). A
    weighted mean never overshoots the wanted values (no ringing before or after a span), and it is as smooth as
    the Gaussian."""
    if sigma <= 0 or wanted.shape[0] < 2:
        return wanted.clone()
    radius = max(1, int(round(3.0 * sigma)))
    t = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (t / sigma) ** 2)[None, None, :]
    w = weight.double()[None, None, :]
    num = torch.nn.functional.conv1d((wanted.double() * weight.double()[:, None]).T[:, None, :], kernel, padding=radius)
    den = torch.nn.functional.conv1d(w, kernel, padding=radius)
    return (num[:, 0, :] / den[0].clamp_min(1e-12)).T.to(wanted.dtype)


def least_cost_path(cost: Tensor, levels: Tensor, step_cost: float) -> Tensor:
    """``(F,)`` indices into ``levels (K,)``, one per frame, minimising the summed ``cost (F, K)`` of the chosen
    levels plus ``step_cost * (level change)^2`` between consecutive frames (dynamic programming, exact); an
    infinite cost forbids a level on that frame."""
    f_n = cost.shape[0]
    step = step_cost * (levels[:, None] - levels[None, :]) ** 2  # (from, to)
    total = cost[0].clone()
    back = torch.zeros(f_n, len(levels), dtype=torch.long)
    for f in range(1, f_n):
        total, back[f] = (total[:, None] + step).min(dim=0)
        total = total + cost[f]
    path = torch.zeros(f_n, dtype=torch.long)
    path[-1] = total.argmin()
    for f in range(f_n - 1, 0, -1):
        path[f - 1] = back[f, path[f]]
    return path


__all__ = ["bspline_basis", "close_caps", "cubic_bspline", "fallback_weights", "knot_count", "least_cost_path",
           "smoothstep", "weighted_smooth"]
