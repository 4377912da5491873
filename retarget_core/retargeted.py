"""What the pipeline computed for one job, in memory: shared by the pipeline, the metrics JSON and the CLI."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from torch import Tensor

from retarget_core.body_cache import BodyAssets
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.jobs import JobInputs
from retarget_core.loading import LoadedCharacter, LoadedMotion
from retarget_core.measure import SourceContactResult
from retarget_core.motion import Motion


@dataclass
class Prepared:
    """Everything up to the copy baseline: the inputs as read, the source motion on its own body
    (``source_view``), the contacts found on it and carried to the target, and "before" on the target."""

    inputs: JobInputs
    source: LoadedMotion
    source_body: LoadedCharacter
    target: LoadedCharacter
    source_view: Motion
    contacts: SourceContactResult
    constraints: ContactConstraints
    target_feet: FootContacts
    before: Motion
    assets: BodyAssets
    warnings: list[str] = field(default_factory=list)
    body_cached: bool = False
    # (F, 2) left/right foot of the source planted, as the judge defines it (on the source body).
    source_planted: Tensor | None = None
    # (F, 2) how far each source toe stands above its rest height (m at 1.80 m), as the judge reads it.
    source_toe_heights: Tensor | None = None


@dataclass
class Retargeted:
    """A job's motions: :class:`Prepared` plus "after" and what each refinement stage did.

    stage_reports: stage name -> that stage's JSON-ready report (frames changed, figures before/after)."""

    prepared: Prepared
    after: Motion
    stages_run: list[str]
    stages_skipped: list[str]
    stage_reports: dict[str, dict[str, Any]]
    warnings: list[str]

    # Shortcuts to what most readers want.
    @property
    def source(self) -> LoadedMotion:
        return self.prepared.source

    @property
    def source_body(self) -> LoadedCharacter:
        return self.prepared.source_body

    @property
    def source_view(self) -> Motion:
        return self.prepared.source_view

    @property
    def target(self) -> LoadedCharacter:
        return self.prepared.target

    @property
    def before(self) -> Motion:
        return self.prepared.before


__all__ = ["Prepared", "Retargeted"]
