"""Floor stage: the whole body raised where it sinks below the floor (ACCEPTANCE.md "ground penetration"), by a
root lift of least jerk.

Why: on cartwheels, kneeling and dance drops the capture itself goes below its floor while its planted feet stand
on it, so the copy and every stage after it inherit a body 2 to 10 cm under y = 0 on those frames (the collision
stage keeps feet from going deeper and turns a hand up only beside a planted foot; the foot lock lifts the body only by its free feet's
depth). A lift that follows each frame's depth exactly, or fades in over a few frames, adds jerk (a probe,
docs/results.md: jerk ratio 1.10 -> 1.16 to 1.38). Here the lift ``L (F,)`` is the bounded least-squares solution
of

    minimise  sum (third difference of L)^2 + size_weight * sum L^2      (per frame at 30 fps)
    subject to  L >= depth of the lowest body vertex, where deeper than the judge's allowance,
                L <= float_m - height of each planted foot's lowest vertex (the source's plants)

so it rises and falls as smoothly as the frames it must clear allow, is zero far from them, and never lifts a
planted foot off the floor by more than the judge's float allowance (a knee or hand sunk while a foot is planted
is lifted only that far). Accessories (a staff, a cloak: not the body) do not count. Last, a guard: the lift is
scaled down until the result's jerk is within the judge's bound (1.1 x the source's) or the input's own.
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
from retarget_core.metrics.feet_acceptance import lowest_foot_heights
from retarget_core.motion import Motion

REFERENCE_HEIGHT_M = 1.80


@dataclass(frozen=True)
class FloorParams:
    """Lengths at a 1.80 m character (scaled to the body)."""

    sunk_m: float = 0.005  # frames sunk deeper than this are lifted (ACCEPTANCE.md: ground penetration <= 0.5 cm)
    float_m: float = 0.01  # a planted foot is not lifted higher than this (ACCEPTANCE.md float: at most 1 cm)
    size_weight: float = 1e-4  # the lift's size against its jerk: zero away from the frames it clears
    jerk_ratio: float = 1.1  # the lift is scaled down until the jerk is within this x the source's (ACCEPTANCE.md)


def least_jerk_lift(depth: Tensor, ceiling: Tensor, fps: float, size_weight: float) -> Tensor:
    """``(F,)`` the lift of least third difference (per frame at 30 fps) plus ``size_weight`` times its size, at
    least ``depth (F,)`` and at most ``ceiling (F,)`` (``inf``: none; ``depth`` wins where they cross)."""
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


def planted_feet(ctx: RefineContext) -> Tensor:
    """``(F, 2)`` left and right foot of the source planted (the judge's labels where known, else the detector's
    toe or heel)."""
    if ctx.planted is not None:
        return ctx.planted.bool()
    labels = ctx.feet.labels.bool()
    return torch.stack([labels[:, 0] | labels[:, 1], labels[:, 2] | labels[:, 3]], dim=1)


def body_heights(ctx: RefineContext, motion: Motion) -> tuple[Tensor, Tensor]:
    """``(F,)`` height of the lowest body vertex (accessories left out) and ``(F, 2)`` of each foot's lowest vertex
    (m)."""
    grot, gpos = motion.global_transforms()
    body = ctx.parts.body
    index = torch.arange(ctx.target.num_vertices) if body is None else torch.nonzero(body).flatten()
    lowest = ctx.target.lowest_heights(index, grot, gpos)
    return lowest.double(), lowest_foot_heights(ctx.target, ctx.target_mapping, motion).double()


def lift_ceiling(planted: Tensor, foot: Tensor, float_m: float) -> Tensor:
    """``(F,)`` the most each frame may be lifted: ``float_m`` less the height of its highest planted foot
    (``planted (F, 2)``, ``foot (F, 2)`` each foot's lowest vertex; a sunk planted foot may come up), ``inf`` where
    no foot is planted. A free foot does not count: the judge's float reads the planted feet only."""
    highest = torch.where(planted, foot, -torch.inf).amax(-1)
    return torch.where(planted.any(-1), (float_m - highest).clamp_min(0.0), torch.inf)


def canonical_joints(motion: Motion, joints: dict[str, int], names: list[str], height: float) -> Tensor:
    """``(F, C, 3)`` world positions of the canonical joints ``names`` (their indices in ``joints``), at 1.80 m."""
    _, gpos = motion.global_transforms()
    return gpos[:, [joints[n] for n in names]].double() * (REFERENCE_HEIGHT_M / height)


def mean_jerk(j3: Tensor) -> float:
    """Mean norm of third differences ``j3 (F-3, C, 3)`` (the judge's jerk)."""
    return float(j3.norm(dim=-1).mean()) if j3.numel() else 0.0


def jerk_share(ctx: RefineContext, motion: Motion, lift: Tensor, ratio: float) -> float:
    """The largest share ``a`` in [0, 1] of ``lift (F,)`` (m) whose result's jerk stays within ``ratio`` x the
    source's or the input's own (the jerk is convex in ``a``: bisection)."""
    names = [n for n in ctx.target_mapping.joints if n in ctx.source_mapping.joints]
    src = canonical_joints(ctx.source_view, ctx.source_mapping.joints, names, ctx.source_body.height)
    tgt = canonical_joints(motion, ctx.target_mapping.joints, names, ctx.target.height)
    if len(tgt) < 4 or len(src) < 4:
        return 1.0
    j3 = third_difference(tgt)
    lift3 = third_difference(lift.double() * (REFERENCE_HEIGHT_M / ctx.target.height))
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)

    def jerk_at(a: float) -> float:
        return mean_jerk(j3 + a * lift3[:, None, None] * up)

    limit = max(ratio * mean_jerk(third_difference(src)), jerk_at(0.0))
    if jerk_at(1.0) <= limit:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if jerk_at(mid) <= limit else (lo, mid)
    return lo


def third_difference(x: Tensor) -> Tensor:
    """``(F-3, ...)`` third differences along the first axis of ``x (F, ...)``."""
    return x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]


def run(ctx: RefineContext, motion: Motion, params: FloorParams | None = None) -> StageOutcome:
    """Lift the root of ``motion`` where its body sinks below y = 0 (see the module doc)."""
    p = params or FloorParams()
    to_body = ctx.target.height / REFERENCE_HEIGHT_M
    with torch.no_grad():
        lowest, foot = body_heights(ctx, motion)
    depth = (-lowest).clamp_min(0.0)
    sunk = depth > p.sunk_m * to_body
    report: dict[str, float | int] = {
        "frames_below_floor": int(sunk.sum()),
        "ground_penetration_cm_before": round(float(depth.mean()) * 100.0 / to_body, 3) if len(depth) else 0.0,
    }
    if not bool(sunk.any()):
        return StageOutcome(motion, {**report, "frames_changed": 0})
    feet = planted_feet(ctx)[: len(depth)]
    planted = feet.any(-1)
    ceiling = lift_ceiling(feet, foot, p.float_m * to_body)
    lift = least_jerk_lift(torch.minimum(torch.where(sunk, depth, 0.0), ceiling), ceiling, motion.fps, p.size_weight)
    share = jerk_share(ctx, motion, lift, p.jerk_ratio)
    lift = lift * share
    trans = motion.translations.clone()
    roots = [j for j, parent in enumerate(motion.skeleton.parents) if parent < 0]  # each moves its whole subtree
    trans[:, roots, 1] += lift.to(trans.dtype)[:, None]
    changed = lift > 1e-6 * to_body
    report.update({
        "frames_changed": int(changed.sum()),
        "max_lift_cm": round(float(lift.max()) * 100.0 / to_body, 3),
        "planted_frames_lifted": int((changed & planted).sum()),
        "jerk_share": round(share, 3),
        "ground_penetration_cm_after": round(float((depth - lift).clamp_min(0.0).mean()) * 100.0 / to_body, 3),
    })  # fmt: skip
    return StageOutcome(Motion(motion.skeleton, motion.fps, motion.rotations.clone(), trans, motion.name), report)


__all__ = ["FloorParams", "least_jerk_lift", "planted_feet", "run"]
