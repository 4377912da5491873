"""What every refinement stage may read: the target, its parts and SDFs, the source on its body, the contacts
to keep, the planted feet, the options and the device. Built once per job by the pipeline."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import torch

from retarget_core.body_parts import BodyParts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.contacts.self_contact import SelfContacts
from retarget_core.energy.sdf import PartSDF
from retarget_core.motion import Motion
from retarget_core.options import RetargetOptions


@dataclass
class RefineContext:
    """Inputs shared by the refinement stages of one job (all motions ``F`` frames at ``before.fps``).

    target, target_mapping: the character being animated and its canonical joint mapping.
    parts, sdf: its body parts and per-part signed-distance grids (cached per body, see ``body_cache``).
    source_body, source_mapping, source_view: the source motion performed by the source's own body.
    self_contacts: hand self-contacts detected on the source body (source vertex indices).
    constraints: the same contacts as target vertex pairs ``(M,)`` per frame (what a stage must keep).
    feet: planted-foot labels ``(F, 4)`` of the source (left toe, left heel, right toe, right heel), on the
        target's joints (``feet.joints`` index the target skeleton).
    planted: ``(F, 2)`` bool, left and right foot of the source planted as ACCEPTANCE.md defines it (toe low,
        toe and ankle still, majority-smoothed; :func:`metrics.feet_acceptance.planted_feet`); None: derive
        from ``feet`` (toe and heel).
    toe_heights: ``(F, 2)`` how far each source toe joint (the ankle without toes) stands above its rest height,
        metres at a 1.80 m character (:func:`metrics.feet_acceptance.toe_heights`); None: unknown.
    before: the copy baseline every stage's effect is measured against.
    options: the job's options; device: where stages make their tensors.
    progress: called with the fraction 0..1 of the current stage done (optional).
    """

    target: Character
    target_mapping: JointMapping
    parts: BodyParts
    sdf: PartSDF
    source_body: Character
    source_mapping: JointMapping
    source_view: Motion
    self_contacts: SelfContacts
    constraints: ContactConstraints
    feet: FootContacts
    before: Motion
    planted: torch.Tensor | None = None
    toe_heights: torch.Tensor | None = None
    options: RetargetOptions = field(default_factory=RetargetOptions)
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    progress: Callable[[float], None] | None = None

    @property
    def num_frames(self) -> int:
        return self.before.num_frames

    def report_progress(self, fraction: float) -> None:
        """Tell the job how far the running stage is (0..1)."""
        if self.progress is not None:
            self.progress(min(1.0, max(0.0, fraction)))


@dataclass
class StageOutcome:
    """What a refinement stage returns: the refined motion (same skeleton and frame count as its input) and a
    JSON-ready report of what it changed (``frames_changed`` and stage-specific figures)."""

    motion: Motion
    report: dict[str, Any] = field(default_factory=dict)


RefineStage = Callable[[RefineContext, Motion], StageOutcome]
"""A refinement stage: ``(context, motion so far) -> outcome``."""


P = TypeVar("P")


def computes_on_cpu(stage: Callable[[RefineContext, Motion, P | None], StageOutcome],
                    ) -> Callable[[RefineContext, Motion, P | None], StageOutcome]:  # fmt: skip
    """A stage ``run(ctx, motion, params=None)`` that computes on the CPU: a motion on another device is moved to
    the CPU for it and its result moved back."""

    def run(ctx: RefineContext, motion: Motion, params: P | None = None) -> StageOutcome:
        device = motion.rotations.device
        if device.type == "cpu":
            return stage(ctx, motion, params)
        outcome = stage(ctx, motion.to(torch.device("cpu")), params)
        return StageOutcome(outcome.motion.to(device), outcome.report)

    run.__doc__, run.__name__ = stage.__doc__, getattr(stage, "__name__", "run")
    return run


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (CUDA when available) as a torch device; a CUDA device that is
    not there falls back to the CPU with no error (the job's warnings say so)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        return torch.device("cpu")
    return torch.device(name)


__all__ = ["RefineContext", "RefineStage", "StageOutcome", "computes_on_cpu", "resolve_device"]
