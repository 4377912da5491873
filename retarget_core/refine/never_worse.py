"""The never-worse check both collision stages end with: every changed frame is measured with all vertices, and
where penetration or a contact got worse than in the input the change is repaired (when the stage can) or
blended back toward the input, smoothly, in rounds. When the rounds run out, what is still worse or unmeasured
goes back to the input with the same blend (:func:`settle`), never with a step: a step in a limb's rotation is
what the judge's jerk reads most.

A stage gives two callbacks: ``measure(weight, frames)`` measures its result with the change scaled by
``weight (F,)`` on clip ``frames (n,)``; ``repair(after, worse)`` (optional) tries to mend the worse frames and
returns the frames to measure again, or None when it has nothing left to try.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.refine.collision_check import ContactInstances, FrameCheck, WorseLimits, worse_frames
from retarget_core.refine.temporal import fallback_weights


@dataclass(frozen=True)
class FallbackSettings:
    """How a worse frame's change is withdrawn: scaled by ``factor`` per round, dropped below ``floor``, blended
    over ``ramp`` frames (at the clip's rate); ``rounds`` rounds."""

    rounds: int
    factor: float
    floor: float
    ramp: int


Measure = Callable[[Tensor, Tensor], FrameCheck]
Repair = Callable[[FrameCheck, Tensor], "Tensor | None"]


@dataclass
class NeverWorse:
    """The check's state: ``before`` (the input, every frame), ``final`` (the figures of the result so far),
    ``weight (F,)`` the share of the change kept per frame, ``cap (F,)`` its ceiling where it was worse."""

    before: FrameCheck
    final: FrameCheck
    weight: Tensor
    cap: Tensor
    contacts: ContactInstances
    settle_rounds: int = 0  # rounds :func:`settle` took

    @classmethod
    def start(cls, before: FrameCheck, contacts: ContactInstances) -> NeverWorse:
        f_n = len(before.frames)
        return cls(before, copy_check(before), torch.ones(f_n), torch.ones(f_n), contacts)

    def merge(self, after: FrameCheck) -> None:
        """The measured frames of ``after`` replace the result's figures (contacts where measured)."""
        idx = after.frames
        self.final.volume[idx], self.final.max_depth[idx] = after.volume, after.max_depth
        self.final.count[idx] = after.count
        measured = ~torch.isnan(after.contact)
        self.final.contact[measured] = after.contact[measured]

    def restore(self, frames: Tensor) -> None:
        """Frames that are the input's again read the input's figures."""
        if len(frames) == 0:
            return
        b, f = self.before, self.final
        f.volume[frames], f.max_depth[frames], f.count[frames] = b.volume[frames], b.max_depth[frames], b.count[frames]
        if self.contacts.count:
            back = torch.isin(self.contacts.frame, frames)
            f.contact[back] = b.contact[back]

    def fall_back(self, bad: Tensor, s: FallbackSettings) -> Tensor:
        """Scale the change down on frames ``bad`` and ramp around them; the frames whose weight changed and is
        still above zero (to measure again)."""
        scaled = self.weight[bad] * s.factor
        self.cap[bad] = torch.where(scaled < s.floor, torch.zeros_like(scaled), scaled)
        return self._blend_to_caps(s.ramp)

    def give_up(self, frames: Tensor, ramp: int) -> Tensor:
        """The change on ``frames`` goes back to the input, blended over ``ramp`` frames like a fallback (no step
        where a kept change meets a withdrawn one); the frames around them whose weight fell (to measure again)."""
        self.cap[frames] = 0.0
        return self._blend_to_caps(ramp)

    def _blend_to_caps(self, ramp: int) -> Tensor:
        """Weights lowered to the blend of :attr:`cap` (at most the cap on every frame, so 0 where it is 0); frames
        back at the input read its figures. The frames whose weight fell and is still above zero."""
        new_w = torch.minimum(self.weight, fallback_weights(self.cap, ramp))
        lowered = torch.nonzero(new_w < self.weight - 1e-6).flatten()
        self.weight = new_w
        self.restore(lowered[new_w[lowered] == 0])
        return lowered[new_w[lowered] > 0]


def copy_check(c: FrameCheck) -> FrameCheck:
    """A copy of ``c`` whose per-frame figures can be changed in place (``depth`` shared)."""
    return FrameCheck(c.frames, c.volume.clone(), c.max_depth.clone(), c.count.clone(), c.depth, c.contact.clone())


def run_never_worse(state: NeverWorse, frames: Tensor, measure: Measure, limits: WorseLimits, scale: float,
                    settings: FallbackSettings, repair: Repair | None = None,
                    repair_rounds: int = 0) -> NeverWorse:  # fmt: skip
    """Measure the changed ``frames``, repair or fall back where worse, until nothing is worse (``limits`` and
    ``scale`` as :func:`worse_frames`); ``state.weight`` ends as the share of the change to keep per frame."""
    repairs = 0
    for _ in range(settings.rounds + repair_rounds):
        if len(frames) == 0:
            break
        after = measure(state.weight, frames)
        worse = worse_frames(state.before, after, state.contacts, limits, scale)
        if not bool(worse.any()):
            state.merge(after)
            frames = frames[:0]
            break
        if repair is not None and repairs < repair_rounds:
            again = repair(after, worse)
            if again is not None:
                repairs += 1
                frames = again
                continue
        state.merge(after)
        frames = state.fall_back(frames[worse], settings)
    settle(state, frames, measure, limits, scale, settings)
    return state


def settle(
    state: NeverWorse, frames: Tensor, measure: Measure, limits: WorseLimits, scale: float, settings: FallbackSettings
) -> None:
    """The rounds ran out with ``frames`` unmeasured: measure them; worse ones go back to the input, blended over
    the ramp, and the blend's frames are measured next, until none is worse. Each round sends at least one more
    frame back to the input, so it ends within ``F`` rounds; a round measures only the blend's frames."""
    while len(frames):
        after = measure(state.weight, frames)
        worse = worse_frames(state.before, after, state.contacts, limits, scale)
        state.merge(after)
        state.settle_rounds += 1
        frames = state.give_up(frames[worse], settings.ramp)


__all__ = ["FallbackSettings", "NeverWorse", "copy_check", "run_never_worse", "settle"]
