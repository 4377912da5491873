"""Elbow swivel: each arm turned about its shoulder-to-wrist axis, out of the body where the judge reads it inside
(issue 22, item 3: the frames deeper than 1 cm left after the collision stage are upper arms at the front of a
heavy chest or beside the armpit, on poses a joint rotation can change; docs/collisions.md).

Why this move: turning the whole arm about the line from shoulder to wrist swings the elbow and keeps the wrist
where it is, and the hand keeps its world rotation, so the hands (the end effectors the judge reads) and their
contacts do not move. The collision stage cannot see most of these vertices inside (its rigid part SDFs read
them outside), and the posed-mesh lever it has costs end-effector error (docs/collisions.md).

1. Measure, per frame and arm, the deepest of its sampled vertices (not its hand's) inside a part the judge tests
   it against, and of the legs' vertices inside it, on the judge's closed parts
   (:func:`retarget_core.contacts.arm_depth.arm_penetration`).
2. Search: where an arm is deeper than ``search_m``, each turn of ``turns_deg`` is posed and measured the same
   way; the shallowest wins (no turn on ties, then the smaller turn). A search, not a gradient step: a local
   (plane) model of the depth, tried first, got a third of the gain, since a deep elbow often has to swing
   30 to 70 degrees round the chest to come out.
3. Smooth in time (:func:`retarget_core.refine.temporal.weighted_smooth`: weight 1 where the arm is in the
   body, ``free_weight`` elsewhere, toward no turn), then the never-worse check on the judge's parts
   (:func:`retarget_core.refine.judged_check.never_worse_weights`): a frame whose judged arm penetration grew is
   withdrawn smoothly.

Lengths at a 1.80 m character (scaled to the body). Computes on the CPU, a chunk of frames at a time: the turns
of a chunk's frames are measured on its parts, posing and refitting again only what a turn moves
(:class:`retarget_core.contacts.hand_reach.MovedParts`), and the never-worse check's "before" is read in the same
pass (all equal to measuring each turn afresh).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from retarget_core.contacts.arm_depth import arm_penetration, arm_penetration_and_depth
from retarget_core.contacts.hand_reach import (
    MovedParts,
    PosedParts,
    ReachBody,
    posed_chunks,
    posed_for_reach,
    posed_moved,
    reach_body,
)
from retarget_core.context import RefineContext, StageOutcome, computes_on_cpu
from retarget_core.motion import Motion
from retarget_core.refine.arms import Arm, arms_of, swivel_arms
from retarget_core.refine.judged_check import ARM_DEPTH_CAP_M, ArmFigures, never_worse_weights
from retarget_core.refine.temporal import weighted_smooth

DEEP_M = 0.01  # ACCEPTANCE.md: frames > 1 cm (what the report counts)


@dataclass(frozen=True)
class SwivelParams:
    """Lengths at a 1.80 m character."""

    search_m: float = 0.005  # frames where an arm is deeper than this are searched for a turn
    turns_deg: tuple[float, ...] = (-10.0, 10.0, -20.0, 20.0, -35.0, 35.0, -50.0, 50.0, -70.0, 70.0)  # tried, smaller
    # first; without the 10 and 35 degree steps, 005_12 x heldout_tall read 43 % frames > 1 cm, not 15 (the chain's 30)
    smooth_seconds: float = 0.1  # the turns' smoothing in time (a Gaussian's standard deviation)
    free_weight: float = 0.1  # a frame whose arm is not in the body: weakly toward no turn
    chunk: int = 64  # frames posed together, at most (fewer on a body whose part trees would not fit: ReachBody)


@dataclass
class ArmFrames:
    """Per frame and arm ``(F, 2)``: the wanted turn (radians), the smoothing weight, and whether a sampled arm
    point is in the body (``inside``) or deeper than 1 cm (``deep``)."""

    wanted: Tensor
    weight: Tensor
    inside: Tensor
    deep: Tensor


def arm_depths(ctx: RefineContext, rb: ReachBody, motion: Motion, frames: Tensor, sides: list[int],
               chunk: int) -> Tensor:  # fmt: skip
    """``(n, 2)`` the deepest sampled point of each of arms ``sides``' judged penetration (arm_penetration,
    without its hand's points: a swivel keeps the hand; 0 for the other side) at clip ``frames (n,)``."""
    out = torch.zeros(len(frames), 2, dtype=torch.float64)
    s = 0
    for fr, posed in posed_chunks(rb, ctx.target, motion, frames, chunk):
        pp = PosedParts(rb, posed)
        for side in sides:
            out[s : s + len(fr), side] = arm_penetration(pp, side, ARM_DEPTH_CAP_M * rb.scale, with_hand=False)[1]
        s += len(fr)
    return out


def repeated(motion: Motion, frames: Tensor, times: int) -> Motion:
    """A motion of ``frames (n,)`` of ``motion`` repeated ``times`` times (``n * times`` frames)."""
    idx = frames.repeat(times)
    return Motion(motion.skeleton, motion.fps, motion.rotations[idx], motion.translations[idx], motion.name)


def measure_turns(ctx: RefineContext, rb: ReachBody, motion: Motion, arms: list[Arm],
                  p: SwivelParams) -> tuple[ArmFrames, ArmFigures]:  # fmt: skip
    """:class:`ArmFrames` of ``motion``: each arm's depth on every frame, and on the frames where it is deeper
    than ``search_m`` the turn of ``turns_deg`` that makes it shallowest (no turn, then the smaller, on ties); and
    both arms' :class:`ArmFigures` on every frame (the never-worse check's "before", read on the same parts).
    A chunk of frames at a time: its turns are measured on the parts of its frames (:func:`best_turns`)."""
    f_n = motion.num_frames
    out = ArmFrames(torch.zeros(f_n, 2, dtype=torch.float64), torch.full((f_n, 2), p.free_weight, dtype=torch.float64),
                    torch.zeros(f_n, 2, dtype=torch.bool), torch.zeros(f_n, 2, dtype=torch.bool))  # fmt: skip
    figures = ArmFigures.zeros(f_n)
    turns = torch.deg2rad(torch.tensor(p.turns_deg, dtype=torch.float64))
    cap = ARM_DEPTH_CAP_M * rb.scale
    chunk = rb.chunk_frames(p.chunk)
    for s in range(0, f_n, chunk):
        rows = slice(s, min(s + chunk, f_n))
        frames = torch.arange(f_n)[rows]
        pp = PosedParts(rb, posed_for_reach(rb, ctx.target, motion, frames))
        depths = torch.zeros(len(frames), 2, dtype=torch.float64)
        for side in range(2):  # both, as arm_check reads them
            with_hand, depths[:, side] = arm_penetration_and_depth(pp, side, cap)
            figures.add(rows, *with_hand)
        for arm in arms:
            depth = depths[:, arm.side]
            out.inside[rows, arm.side], out.deep[rows, arm.side] = depth > 0, depth > DEEP_M * rb.scale
            out.weight[frames[depth > 0], arm.side] = 1.0
            search = torch.nonzero(depth > p.search_m * rb.scale).flatten()
            if len(search):
                out.wanted[frames[search], arm.side] = best_turns(ctx, rb, motion, arms, arm, pp, frames, search,
                                                                  depth, turns, chunk)  # fmt: skip
    return out, figures


def best_turns(ctx: RefineContext, rb: ReachBody, motion: Motion, arms: list[Arm], arm: Arm, pp: PosedParts,
               frames: Tensor, search: Tensor, depth: Tensor, turns: Tensor, chunk: int) -> Tensor:  # fmt: skip
    """``(m,)`` the turn of ``turns (T,)`` (or 0) that makes ``arm`` shallowest at rows ``search (m,)`` of the
    chunk of clip ``frames (n,)`` whose parts are ``pp`` and the arm's depths ``depth (n,)``. The turns are
    measured about ``chunk`` frames at a time, their parts made from the chunk's where the turn left them (the
    legs, most of the torso, head and other arm)."""
    m = len(search)
    base = pp.frames(search)
    angles = torch.zeros(len(turns) * m, 2, dtype=torch.float64)
    angles[:, arm.side] = turns.repeat_interleave(m)
    many = swivel_arms(repeated(motion, frames[search], len(turns)), arms, angles)
    poses = posed_moved(rb, ctx.target, many, motion, frames[search], base.posed)
    cap = ARM_DEPTH_CAP_M * rb.scale
    tried = [depth[search][None]]  # no turn first: kept unless a turn is shallower
    group = max(1, chunk // m)  # turns measured together
    for first in range(0, len(turns), group):
        count = min(group, len(turns) - first)
        parts = MovedParts(rb, poses.posed(first, count), base, poses.moved)
        tried.append(arm_penetration(parts, arm.side, cap, with_hand=False)[1].view(count, m))
    best = torch.cat(tried).argmin(dim=0)
    return torch.cat([turns.new_zeros(1), turns])[best]


@computes_on_cpu
def run(ctx: RefineContext, motion: Motion, params: SwivelParams | None = None) -> StageOutcome:
    """Elbows swung out of the body, hands kept (module doc)."""
    p = params or SwivelParams()
    t0 = time.perf_counter()
    arms = arms_of(ctx.target_mapping, ctx.target.skeleton.parents)
    if not arms or motion.num_frames == 0:
        return StageOutcome(motion, {"frames_changed": 0, "note": "no mapped arm", "seconds": 0.0})
    rb = reach_body(ctx.target, ctx.target_mapping)
    first, figures = measure_turns(ctx, rb, motion, arms, p)
    turned = torch.stack([weighted_smooth(first.wanted[:, s : s + 1], first.weight[:, s], p.smooth_seconds * motion.fps)[:, 0]
                          for s in range(2)], dim=1)  # fmt: skip
    f_n = motion.num_frames
    changed = torch.nonzero(turned.abs().amax(dim=1) > 1e-4).flatten()
    share = torch.ones(f_n, dtype=torch.float64)
    if len(changed):
        before = figures.check(changed, ctx.target.num_vertices, changed)
        share = never_worse_weights(ctx, rb, motion, lambda w: swivel_arms(motion, arms, turned * w[:, None]), changed,
                                    before=before)  # fmt: skip
    out = swivel_arms(motion, arms, turned * share[:, None])
    return StageOutcome(out, _report(first, turned, share, changed, t0))


def _report(first: ArmFrames, turned: Tensor, share: Tensor, changed: Tensor, t0: float) -> dict[str, Any]:
    """The stage's figures: frames changed and withdrawn, the turns, and the input's frames with an arm in the
    body (sampled points, as the judge's parts read them)."""
    kept = (turned * share[:, None]).abs()
    return {"frames_changed": len(changed), "withdrawn_frames": int((share[changed] < 1.0).sum()),
            "max_turn_deg": round(math.degrees(float(kept.max())) if kept.numel() else 0.0, 1),
            "mean_turn_deg": round(math.degrees(float(kept[changed].mean())) if len(changed) else 0.0, 2),
            "frames_arm_inside_before": int(first.inside.any(dim=1).sum()),
            "frames_arm_deeper_1cm_before": int(first.deep.any(dim=1).sum()),
            "seconds": round(time.perf_counter() - t0, 3)}  # fmt: skip
