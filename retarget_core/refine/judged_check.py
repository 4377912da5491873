"""The never-worse check of the stages that move arms after the collision stage (hand contacts, elbow swivel),
with the arms' penetration read as the judge reads it (:func:`retarget_core.contacts.arm_depth.arm_penetration`
on the judge's closed parts): where a changed frame got worse, the change is withdrawn smoothly
(:mod:`retarget_core.refine.never_worse`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.contacts.arm_depth import arm_penetration
from retarget_core.contacts.hand_reach import PosedParts, ReachBody, posed_chunks
from retarget_core.context import RefineContext
from retarget_core.metrics.depth import VertexDepths
from retarget_core.motion import Motion
from retarget_core.refine.collision_check import ContactInstances, FrameCheck
from retarget_core.refine.collision_params import CollisionParams, at_fps
from retarget_core.refine.never_worse import FallbackSettings, NeverWorse, run_never_worse

ARM_DEPTH_CAP_M = 0.10  # arm vertices deeper than this in a part count at this depth (at 1.80 m)
# Frames (at 30 fps) over which a change that made a frame worse is withdrawn: about the arm stages' own smoothing
# (0.1 s), not the collision stage's 8, so a few worse frames do not take their neighbours' moves (docs/contacts.md)
ARM_WITHDRAW_RAMP = 4

# (moved motion, frames (n,), their arm check) -> the check with the stage's own verdicts (flagged, excused frames)
Verdict = Callable[[Motion, Tensor, FrameCheck], FrameCheck]


@dataclass
class ArmFigures:
    """Per frame ``(n,)`` both arms' penetration as :func:`arm_check` reads it: ``volume`` the sampled depths
    times their samples' areas (m^3), ``max_depth`` the deepest, ``count`` how many."""

    volume: Tensor
    max_depth: Tensor
    count: Tensor

    @classmethod
    def zeros(cls, n: int) -> ArmFigures:
        return cls(torch.zeros(n), torch.zeros(n), torch.zeros(n))

    def add(self, rows: slice, count: Tensor, deepest: Tensor, volume: Tensor) -> None:
        """One arm's :func:`arm_penetration` ``(m,)`` on frames ``rows`` added in."""
        self.count[rows] += count
        self.max_depth[rows] = torch.maximum(self.max_depth[rows], deepest.float())
        self.volume[rows] += volume.float()

    def check(self, frames: Tensor, num_vertices: int, rows: Tensor | None = None) -> FrameCheck:
        """The :class:`FrameCheck` of clip ``frames (n,)`` from these figures' ``rows (n,)`` (default: all)."""
        pick = slice(None) if rows is None else rows
        depth = VertexDepths.empty(len(frames), num_vertices)
        return FrameCheck(frames, self.volume[pick], self.max_depth[pick], self.count[pick], depth, torch.zeros(0))


def arm_check(ctx: RefineContext, rb: ReachBody, motion: Motion, frames: Tensor, chunk: int = 64) -> FrameCheck:
    """Both arms' penetration as the judge reads it (sampled arm vertices inside the parts it tests them against)
    on clip ``frames (n,)``, as a :class:`FrameCheck` for the never-worse check (:class:`ArmFigures`)."""
    figures = ArmFigures.zeros(len(frames))
    cap = ARM_DEPTH_CAP_M * rb.scale
    s = 0
    for fr, posed in posed_chunks(rb, ctx.target, motion, frames, chunk):
        pp = PosedParts(rb, posed)
        for side in range(2):
            figures.add(slice(s, s + len(fr)), *arm_penetration(pp, side, cap))
        s += len(fr)
    return figures.check(frames, ctx.target.num_vertices)


def spread_check(check: FrameCheck, num_frames: int, num_vertices: int) -> FrameCheck:
    """``check`` as a check of every clip frame (zeros on the frames it did not measure: they never change)."""
    vol, mx, cnt = torch.zeros(num_frames), torch.zeros(num_frames), torch.zeros(num_frames)
    vol[check.frames], mx[check.frames], cnt[check.frames] = check.volume, check.max_depth, check.count
    return FrameCheck(torch.arange(num_frames), vol, mx, cnt, VertexDepths.empty(num_frames, num_vertices), check.contact)


def never_worse_weights(ctx: RefineContext, rb: ReachBody, motion: Motion, moved: Callable[[Tensor], Motion],
                        changed: Tensor, verdict: Verdict | None = None, before: FrameCheck | None = None,
                        ramp: int = ARM_WITHDRAW_RAMP) -> Tensor:  # fmt: skip
    """``(F,)`` the share of a stage's change kept per frame: the collision stage's never-worse check on the
    ``changed (n,)`` frames, with the arms' penetration as the judge reads it (:func:`arm_check`); ``moved(weight
    (F,))`` is the input with the change scaled per frame; ``verdict`` marks further frames as worse, or excuses
    their deeper penetration; ``before``:
    the input's :func:`arm_check` on ``changed`` where the stage has it already (measured otherwise); ``ramp``:
    frames at 30 fps over which a withdrawal blends."""
    cp = CollisionParams()
    no_contacts = ContactInstances(*(torch.zeros(0, dtype=torch.long),) * 3)

    def measure(weight: Tensor, frames: Tensor) -> FrameCheck:
        out = moved(weight)
        check = arm_check(ctx, rb, out, frames)
        return check if verdict is None else verdict(out, frames, check)

    if before is None:
        before = arm_check(ctx, rb, motion, changed)
    before = spread_check(before, motion.num_frames, ctx.target.num_vertices)
    settings = FallbackSettings(cp.fallback_rounds, cp.fallback_factor, cp.fallback_floor,
                                at_fps(ramp, motion.fps))  # fmt: skip
    check = run_never_worse(NeverWorse.start(before, no_contacts), changed, measure, cp, 1.0 / rb.scale, settings)
    return check.weight


__all__ = ["ARM_WITHDRAW_RAMP", "ArmFigures", "arm_check", "never_worse_weights", "spread_check"]
