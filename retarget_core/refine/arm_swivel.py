"""Elbow swivel: each arm turned about its shoulder-to-wrist axis, out of the body where the judge reads it inside
(issue 22, item 3: the frames deeper than 1 cm left after the collision stage are upper arms at the front of a
heavy chest or beside the armpit, on poses a joint rotation can change; docs/collisions.md).

Why this move: turning the whole arm about the line from shoulder to wrist swings the elbow and keeps the wrist
where it is, and the hand keeps its world rotation, so the hands (the end effectors the judge reads) and their
contacts do not move. The collision stage cannot see most of these vertices inside (its rigid part SDFs read
them outside), and the posed-mesh lever it has costs end-effector error (docs/collisions.md).

1. Measure, per frame and arm, the deepest of its sampled vertices (not its hand's) inside a part the judge tests
   it against, and of the legs' vertices inside it, on the judge's closed parts
   (:func:`retarget_core.contacts.arm_depth.arm_search_figures`; the turned arm reads the legs only on the frames
   where they were in it unturned: elsewhere its tree is not refit per turn, and the check reads them).
2. Search: where an arm is deeper than ``search_m``, and ``margin_seconds`` around such frames, each turn of
   ``turns_deg`` is posed and measured the same way. A search, not a gradient step: a local (plane) model of
   the depth, tried first, got a third of the gain, since a deep elbow often has to swing 30 to 70 degrees
   round the chest to come out.
3. Choose a path in time: per arm, the sequence of measured turns with the least summed depth plus a cost on
   each change between frames (``step_cost_m``; dynamic programming, :func:`least_cost_path`), among the turns
   the never-worse check would keep as far as the arm's own points tell (:func:`accepted_turns`: volume and
   depth), lightly smoothed. Every frame's turn is one that was measured and accepted, so the check finds few
   frames worse; the best turn per frame, smoothed in time, put unmeasured turns between measured ones, and the
   withdrawals of those spread over the span (docs/collisions.md).
4. The never-worse check on the judge's parts (:func:`retarget_core.refine.judged_check.never_worse_weights`,
   :func:`checked_turns`): a frame whose smoothed turn made the judged arm penetration grow eases back to the
   path's own turn; one still worse there is withdrawn; both smoothly.

Lengths at a 1.80 m character (scaled to the body). Computes on the CPU, a chunk of frames at a time: the turns
of a chunk's frames are measured on its parts, posing and refitting again only what a turn moves
(:class:`retarget_core.contacts.hand_reach.MovedParts`; equal to measuring each turn afresh), and the never-worse
check's "before" is read with the unturned depths.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from retarget_core.contacts.arm_depth import arm_penetration_and_search, arm_search_figures
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
from retarget_core.refine.collision_params import CollisionParams
from retarget_core.refine.judged_check import ARM_DEPTH_CAP_M, ArmFigures, never_worse_weights
from retarget_core.refine.temporal import least_cost_path, weighted_smooth

DEEP_M = 0.01  # ACCEPTANCE.md: frames > 1 cm (what the report counts)
SMALLER_TURN_M = 1e-4  # a turn costs this depth per radian: of two turns about as deep, the smaller wins


@dataclass(frozen=True)
class SwivelParams:
    """Lengths at a 1.80 m character."""

    search_m: float = 0.005  # frames where an arm is deeper than this are searched for a turn
    turns_deg: tuple[float, ...] = (-10.0, 10.0, -20.0, 20.0, -35.0, 35.0, -50.0, 50.0, -70.0, 70.0)  # tried, smaller
    # first; without the 10 and 35 degree steps, 005_12 x heldout_tall read 43 % frames > 1 cm, not 15 (the chain's 30)
    margin_seconds: float = 0.2  # turns are also measured this long around the searched frames: the path eases in
    step_cost_m: float = 0.05  # a change of turn between frames (at 30 fps) costs this much depth per rad^2: at
    # 0.02 the paths step more, and 005_18 x heldout_bulky read jerk 1.0995 against 1.070 (docs/collisions.md)
    smooth_seconds: float = 1.0 / 30.0  # the chosen turns' smoothing in time (a Gaussian's standard deviation)
    chunk: int = 64  # frames posed together, at most (fewer on a body whose part trees would not fit: ReachBody)


@dataclass
class TurnTable:
    """Per frame and arm the deepest sampled arm point (body scale) at each turn of ``levels (K,)`` radians (no
    turn first): ``depth (F, 2, K)``, inf where a turn was not measured, and the arm's points' ``volume (F, 2, K)``
    (:func:`arm_search_figures`); ``inside``, ``deep`` and ``legs_in`` ``(F, 2)``: whether the arm, unturned, is
    in the body, deeper than 1 cm, and holds a leg's point."""

    levels: Tensor
    depth: Tensor
    volume: Tensor
    inside: Tensor
    deep: Tensor
    legs_in: Tensor

    @classmethod
    def unmeasured(cls, levels: Tensor, f_n: int) -> TurnTable:
        """A table of ``f_n`` frames with nothing measured yet."""
        shape = (f_n, 2, len(levels))
        flags = [torch.zeros(f_n, 2, dtype=torch.bool) for _ in range(3)]
        return cls(levels, torch.full(shape, math.inf, dtype=torch.float64), torch.zeros(shape, dtype=torch.float64),
                   *flags)  # fmt: skip


def arm_depths(ctx: RefineContext, rb: ReachBody, motion: Motion, frames: Tensor, sides: list[int],
               chunk: int) -> Tensor:  # fmt: skip
    """``(n, 2)`` each of arms ``sides``' deepest point (:func:`arm_search_figures`; 0 for the other side) at clip
    ``frames (n,)``."""
    out = torch.zeros(len(frames), 2, dtype=torch.float64)
    s = 0
    for fr, posed in posed_chunks(rb, ctx.target, motion, frames, chunk):
        pp = PosedParts(rb, posed)
        for side in sides:
            every = torch.ones(len(fr), dtype=torch.bool)
            out[s : s + len(fr), side] = arm_search_figures(pp, side, ARM_DEPTH_CAP_M * rb.scale, every)[0]
        s += len(fr)
    return out


def repeated(motion: Motion, frames: Tensor, times: int) -> Motion:
    """A motion of ``frames (n,)`` of ``motion`` repeated ``times`` times (``n * times`` frames)."""
    idx = frames.repeat(times)
    return Motion(motion.skeleton, motion.fps, motion.rotations[idx], motion.translations[idx], motion.name)


def measure_turns(ctx: RefineContext, rb: ReachBody, motion: Motion, arms: list[Arm],
                  p: SwivelParams) -> tuple[TurnTable, ArmFigures]:  # fmt: skip
    """:class:`TurnTable` of ``motion``: every turn of ``turns_deg`` measured where an arm is deeper than
    ``search_m`` and within ``margin_seconds`` of such a frame; and both arms' :class:`ArmFigures` on every frame
    (the never-worse check's "before"). A chunk of frames at a time, each posed once: its unturned depths are read
    at once, its turns (:func:`turn_depths`) as soon as the chunks after it reach past its margin, so a chunk's
    parts are kept only that long."""
    f_n = motion.num_frames
    chunk, margin = rb.chunk_frames(p.chunk), round(p.margin_seconds * motion.fps)
    turns = torch.deg2rad(torch.tensor(p.turns_deg, dtype=torch.float64))
    table = TurnTable.unmeasured(torch.cat([turns.new_zeros(1), turns]), f_n)
    figures = ArmFigures.zeros(f_n)
    pending: list[tuple[Tensor, PosedParts]] = []  # chunks whose turns wait for the depths past their margin
    for s in range(0, f_n, chunk):
        frames = torch.arange(s, min(s + chunk, f_n))
        pp = PosedParts(rb, posed_for_reach(rb, ctx.target, motion, frames))
        _measure_unturned(rb, pp, frames, table, figures)
        pending.append((frames, pp))
        read_to = int(frames[-1]) + 1
        search = dilated(table.depth[:, :, 0] > p.search_m * rb.scale, margin)
        while pending and (int(pending[0][0][-1]) + 1 + margin <= read_to or read_to == f_n):
            done, parts = pending.pop(0)
            for arm in arms:
                at = torch.nonzero(search[done, arm.side]).flatten()
                if len(at):
                    legs_on = table.legs_in[done[at], arm.side]
                    depth, volume = turn_depths(ctx, rb, motion, arms, arm, parts, done, at, legs_on, turns, chunk)
                    table.depth[done[at], arm.side, 1:], table.volume[done[at], arm.side, 1:] = depth.T, volume.T
    return table, figures


def _measure_unturned(rb: ReachBody, pp: PosedParts, frames: Tensor, table: TurnTable, figures: ArmFigures) -> None:
    """Each arm's :func:`arm_search_figures` (into ``table``: depth and volume at no turn, inside, deep, legs_in) and both
    arms' :class:`ArmFigures` at clip ``frames (n,)``, whose parts are ``pp``."""
    rows = slice(int(frames[0]), int(frames[-1]) + 1)
    for side in range(2):  # both, as arm_check reads them
        with_hand, (depth, volume, legs_in) = arm_penetration_and_search(pp, side, ARM_DEPTH_CAP_M * rb.scale)
        figures.add(rows, *with_hand)
        table.depth[rows, side, 0], table.volume[rows, side, 0], table.legs_in[rows, side] = depth, volume, legs_in
        table.inside[rows, side], table.deep[rows, side] = depth > 0, depth > DEEP_M * rb.scale


def dilated(mask: Tensor, frames: int) -> Tensor:
    """``(F, C)`` bool: ``mask (F, C)`` grown by ``frames`` frames either way in time."""
    if frames <= 0:
        return mask.clone()
    grown = torch.nn.functional.max_pool1d(mask.T.double()[None], 2 * frames + 1, stride=1, padding=frames)
    return grown[0].T > 0


def turn_depths(ctx: RefineContext, rb: ReachBody, motion: Motion, arms: list[Arm], arm: Arm, pp: PosedParts,
                frames: Tensor, at: Tensor, legs_on: Tensor, turns: Tensor,
                chunk: int) -> tuple[Tensor, Tensor]:  # fmt: skip
    """``(T, m)`` twice: ``arm``'s :func:`arm_search_figures` (the legs read where ``legs_on (m,)``) at each of
    ``turns (T,)`` on rows ``at (m,)`` of the chunk of clip ``frames (n,)`` whose parts are ``pp``. The turns are measured about ``chunk`` frames at
    a time, their parts made from the chunk's where the turn left them (the legs, most of the torso, head and
    other arm)."""
    m = len(at)
    base = pp.frames(at)
    angles = torch.zeros(len(turns) * m, 2, dtype=torch.float64)
    angles[:, arm.side] = turns.repeat_interleave(m)
    many = swivel_arms(repeated(motion, frames[at], len(turns)), arms, angles)
    poses = posed_moved(rb, ctx.target, many, motion, frames[at], base.posed)
    cap = ARM_DEPTH_CAP_M * rb.scale
    depth, volume = [], []
    group = max(1, chunk // m)  # turns measured together
    for _, posed in poses.ways(group):
        count = len(posed) // m
        parts = MovedParts(rb, posed, base, poses.moved)
        d, v = arm_search_figures(parts, arm.side, cap, legs_on.repeat(count))
        depth.append(d.view(count, m))
        volume.append(v.view(count, m))
    return torch.cat(depth), torch.cat(volume)


def accepted_turns(table: TurnTable, before: ArmFigures, scale: float) -> Tensor:
    """``(F, 2, K)`` bool: the measured turns the never-worse check would keep, as far as the arm's own points
    tell (:func:`retarget_core.refine.collision_check.worse_frames` with the collision stage's limits): its
    points' volume grown by no more than the frame's allowance (read on ``before``, both arms' :class:`ArmFigures`
    unturned) and its deepest point not deeper than the frame's. ``scale`` turns body lengths into 1.80 m."""
    limits = CollisionParams()
    vol_before = before.volume.double()[:, None, None] * scale**3
    grow = (table.volume - table.volume[:, :, :1]) * scale**3
    kept = grow <= torch.clamp(limits.worse_volume_fraction * vol_before, min=limits.worse_volume_m3)
    deeper = (table.depth - before.max_depth.double()[:, None, None]) * scale > limits.worse_depth_m
    return kept & ~deeper & torch.isfinite(table.depth)


def coherent_turns(table: TurnTable, accepted: Tensor, arms: list[Arm], p: SwivelParams, fps: float,
                   scale: float) -> Tensor:  # fmt: skip
    """``(F, 2)`` radians: per arm the sequence of ``accepted (F, 2, K)`` turns (no turn always is) with the least
    summed depth (at 1.80 m, ``scale`` turns body lengths into it) plus ``step_cost_m`` per squared change between
    frames (per second squared, so at any rate), smaller turns slightly preferred."""
    out = torch.zeros(table.depth.shape[0], 2, dtype=torch.float64)
    step = p.step_cost_m * (fps / 30.0) ** 2
    allowed = accepted.clone()
    allowed[:, :, 0] = True
    for arm in arms:
        cost = table.depth[:, arm.side] * scale + SMALLER_TURN_M * table.levels.abs()[None]
        cost = torch.where(allowed[:, arm.side], cost, math.inf)
        out[:, arm.side] = table.levels[least_cost_path(cost, table.levels, step)]
    return out


def checked_turns(ctx: RefineContext, rb: ReachBody, motion: Motion, arms: list[Arm], path: Tensor,
                  figures: ArmFigures, p: SwivelParams) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """``(F, 2)`` the turns kept, and ``(F,)`` twice, the share of the smoothing kept and of the turn kept. The
    ``path (F, 2)`` smoothed by ``smooth_seconds``; where the never-worse check finds a smoothed turn worse (it
    was not measured: the smoothing goes between measured turns), it eases back to the path's own turn (measured
    and accepted); where a frame is still worse, its turn is withdrawn, each blended over a few frames. ``figures``:
    both arms' :class:`ArmFigures` unturned, on every frame."""
    smooth = weighted_smooth(path, torch.ones(path.shape[0], dtype=torch.float64), p.smooth_seconds * motion.fps)
    f_n = motion.num_frames
    eased, share = torch.ones(f_n, dtype=torch.float64), torch.ones(f_n, dtype=torch.float64)
    changed = torch.nonzero(smooth.abs().amax(dim=1) > 1e-4).flatten()
    if len(changed) == 0:
        return smooth, eased, share
    before = figures.check(changed, ctx.target.num_vertices, changed)
    to_smooth = smooth - path
    eased = never_worse_weights(ctx, rb, motion, lambda w: swivel_arms(motion, arms, path + to_smooth * w[:, None]),
                                changed, before=before)  # fmt: skip
    turned = path + to_smooth * eased[:, None]
    still = torch.nonzero((eased < 1.0) & (turned.abs().amax(dim=1) > 1e-4)).flatten()
    if len(still):
        before = figures.check(still, ctx.target.num_vertices, still)
        share = never_worse_weights(ctx, rb, motion, lambda w: swivel_arms(motion, arms, turned * w[:, None]), still,
                                    before=before)  # fmt: skip
    return turned * share[:, None], eased, share


@computes_on_cpu
def run(ctx: RefineContext, motion: Motion, params: SwivelParams | None = None) -> StageOutcome:
    """Elbows swung out of the body, hands kept (module doc)."""
    p = params or SwivelParams()
    t0 = time.perf_counter()
    arms = arms_of(ctx.target_mapping, ctx.target.skeleton.parents)
    if not arms or motion.num_frames == 0:
        return StageOutcome(motion, {"frames_changed": 0, "note": "no mapped arm", "seconds": 0.0})
    rb = reach_body(ctx.target, ctx.target_mapping)
    table, figures = measure_turns(ctx, rb, motion, arms, p)
    scale = 1.0 / rb.scale
    path = coherent_turns(table, accepted_turns(table, figures, scale), arms, p, motion.fps, scale)
    turned, eased, share = checked_turns(ctx, rb, motion, arms, path, figures, p)
    return StageOutcome(swivel_arms(motion, arms, turned), _report(table, turned, eased, share, t0))


def _report(table: TurnTable, turned: Tensor, eased: Tensor, share: Tensor, t0: float) -> dict[str, Any]:
    """The stage's figures: frames changed, eased back to the path and withdrawn, the turns, and the input's
    frames with an arm in the body (sampled points, as the judge's parts read them)."""
    kept = turned.abs()
    changed = torch.nonzero(kept.amax(dim=1) > 1e-4).flatten()
    return {"frames_changed": len(changed), "eased_frames": int((eased < 1.0).sum()),
            "withdrawn_frames": int((share < 1.0).sum()),
            "max_turn_deg": round(math.degrees(float(kept.max())) if kept.numel() else 0.0, 1),
            "mean_turn_deg": round(math.degrees(float(kept[changed].mean())) if len(changed) else 0.0, 2),
            "frames_arm_inside_before": int(table.inside.any(dim=1).sum()),
            "frames_arm_deeper_1cm_before": int(table.deep.any(dim=1).sum()),
            "seconds": round(time.perf_counter() - t0, 3)}  # fmt: skip
