"""A :class:`RefineContext` for one motion x target outside a job (tests, benchmarks, the evaluation of the
network), built from :func:`retarget_core.pipeline.prepare` the way :func:`retarget_core.pipeline.refine` does."""

from __future__ import annotations

from pathlib import Path

from retarget_core.jobs import JobInputs
from retarget_core.options import RetargetOptions
from retarget_core.refine.context import RefineContext
from retarget_core.retargeted import Prepared


def prepared_case(motion: Path, target: Path | str, max_frames: int | None = None, options: RetargetOptions | None = None) -> Prepared:
    """Everything up to the copy baseline for ``motion`` on ``target`` (first ``max_frames`` frames)."""
    from retarget_core.pipeline import prepare

    return prepare(JobInputs(Path(motion), target, options=options or RetargetOptions()), max_frames=max_frames)


def context_from_prepared(prepared: Prepared, device: str = "cpu") -> RefineContext:
    """The refinement context of a prepared job, as :func:`retarget_core.pipeline.refine_context` builds it, on
    ``device``."""
    from retarget_core.pipeline import refine_context

    return refine_context(prepared, prepared.inputs.options.model_copy(update={"device": device}))


__all__ = ["context_from_prepared", "prepared_case"]
