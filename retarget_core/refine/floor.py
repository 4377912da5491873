"""Floor stage: the whole body raised where it sinks below the floor (ACCEPTANCE.md "ground penetration"), by a
root lift of least jerk.

Why: on cartwheels, kneeling and dance drops the capture itself goes below its floor while its planted feet stand
on it, so the copy and every stage after it inherit a body 2 to 10 cm under y = 0 on those frames (the collision
stage turns hands and feet up but lifts no body). A lift that follows each frame's depth exactly, or fades in over
a few frames, adds jerk (a probe, docs/results.md: jerk ratio 1.10 -> 1.16 to 1.38). Here the lift ``L (F,)`` is
the bounded least-squares solution of

    minimise  sum (fps-scaled third difference of L)^2 + size_weight * sum L^2
    subject to  L >= depth (no vertex below the floor)  and, where a source foot is planted,
                L <= max(depth, float_m - height of the lowest vertex)  (a planted foot stays within the
                judge's float allowance)

so it rises and falls as smoothly as the frames it must clear allow, and is zero far from them.
Lengths in metres on the body's own scale unless the name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import sparse
from scipy.sparse.linalg import splu
from torch import Tensor

from retarget_core.context import RefineContext, StageOutcome
from retarget_core.metrics.feet_acceptance import lowest_vertex_heights
from retarget_core.motion import Motion

REFERENCE_HEIGHT_M = 1.80


@dataclass(frozen=True)
class FloorParams:
    """Lengths at a 1.80 m character (scaled to the body)."""

    sunk_m: float = 0.0005  # frames whose lowest vertex is this far below the floor are lifted (less: rounding)
    float_m: float = 0.01  # a planted foot is not lifted higher than this (ACCEPTANCE.md float: at most 1 cm)
    size_weight: float = 1e-4  # the lift's size against its jerk: zero away from the frames it clears


def least_jerk_lift(depth: Tensor, ceiling: Tensor, fps: float, size_weight: float) -> Tensor:
    """``(F,)`` the lift of least third difference (per frame at 30 fps) plus ``size_weight`` times its size, at
    least ``depth (F,)`` and at most ``ceiling (F,)`` (``inf``: none; never below ``depth``) on every frame."""
    need = depth.double().numpy()
    f_n = len(need)
    if f_n < 4:
        return depth.clone()
    rate = fps / 30.0
    d3 = sparse.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(f_n - 3, f_n))
    # for one curve in time, the sum of squared third differences scales as rate^-5 and the size's as rate
    q = (d3.T @ d3 + (size_weight / rate**6) * sparse.eye(f_n)).tocsc()
    upper = np.maximum(ceiling.double().numpy(), need)
    return torch.from_numpy(box_qp(q, need, upper)).to(depth.dtype)


def box_qp(q: sparse.csc_matrix, lower: np.ndarray, upper: np.ndarray, rounds: int = 100) -> np.ndarray:
    """``(n,)`` the minimiser of ``x^T q x / 2`` (``q (n, n)`` sparse, positive definite) with ``lower <= x <=
    upper``: a primal active set (variables held at a bound are freed when their gradient points inside, free ones
    past a bound are held there), each round one sparse solve on the free variables."""
    x = np.clip(np.zeros(len(lower)), lower, upper)
    at_low, at_high = lower > 0.0, upper < 0.0
    for _ in range(rounds):
        held = at_low | at_high
        x[at_low], x[at_high] = lower[at_low], upper[at_high]
        free = np.nonzero(~held)[0]
        if len(free):
            rhs = -(q[free][:, np.nonzero(held)[0]] @ x[held])
            x[free] = splu(q[free][:, free].tocsc()).solve(rhs)
        grad = q @ x
        low_past, high_past = ~held & (x < lower), ~held & (x > upper)
        release = (at_low & (grad < 0.0)) | (at_high & (grad > 0.0))
        if not (low_past.any() or high_past.any() or release.any()):
            break
        at_low = (at_low & ~release) | low_past
        at_high = (at_high & ~release) | high_past
    return np.clip(x, lower, upper)


def planted_frames(ctx: RefineContext) -> Tensor:
    """``(F,)`` frames on which a source foot is planted (the judge's labels where known, else the detector's)."""
    if ctx.planted is not None:
        return ctx.planted.bool().any(-1)
    return ctx.feet.labels.bool().any(-1)


def run(ctx: RefineContext, motion: Motion, params: FloorParams | None = None) -> StageOutcome:
    """Lift the root of ``motion`` where its lowest vertex is below y = 0 (see the module doc)."""
    p = params or FloorParams()
    to_body = ctx.target.height / REFERENCE_HEIGHT_M
    with torch.no_grad():
        heights = lowest_vertex_heights(ctx.target, motion).double()  # (F,)
    depth = (-heights).clamp_min(0.0)
    report: dict[str, float | int] = {
        "frames_below_floor": int((depth > p.sunk_m * to_body).sum()),
        "ground_penetration_cm_before": round(float(depth.mean()) * 100.0 / to_body, 3) if len(depth) else 0.0,
    }
    if report["frames_below_floor"] == 0:
        return StageOutcome(motion, {**report, "frames_changed": 0})
    planted = planted_frames(ctx)[: len(depth)]
    ceiling = torch.full_like(depth, float("inf"))
    ceiling[planted] = (p.float_m * to_body - heights[planted].clamp_min(0.0)).clamp_min(0.0)
    lift = least_jerk_lift(depth, ceiling, motion.fps, p.size_weight)
    trans = motion.translations.clone()
    roots = [j for j, parent in enumerate(motion.skeleton.parents) if parent < 0]  # each moves its whole subtree
    trans[:, roots, 1] += lift.to(trans.dtype)[:, None]
    changed = lift > 1e-6 * to_body
    report.update({
        "frames_changed": int(changed.sum()),
        "max_lift_cm": round(float(lift.max()) * 100.0 / to_body, 3),
        "planted_frames_lifted": int((changed & planted).sum()),
    })  # fmt: skip
    return StageOutcome(Motion(motion.skeleton, motion.fps, motion.rotations.clone(), trans, motion.name), report)


__all__ = ["FloorParams", "least_jerk_lift", "planted_frames", "run"]
