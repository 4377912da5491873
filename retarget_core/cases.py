"""A :class:`RefineContext` for one motion x target outside a job (tests, benchmarks, the evaluation of the
networks, stage development): exactly what :func:`retarget_core.pipeline.refine` gives the stages. Above the
pipeline: it runs :func:`retarget_core.pipeline.prepare`."""

from __future__ import annotations

from pathlib import Path

from retarget_core.context import RefineContext
from retarget_core.jobs import JobInputs
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import prepare, refine_context
from retarget_core.retargeted import Prepared


def prepared_case(motion: Path, target: Path | str, max_frames: int | None = None,
                  options: RetargetOptions | None = None, skip_frames: int = 0) -> Prepared:  # fmt: skip
    """Everything up to the copy baseline for ``motion`` on ``target`` (a file or ``builtin:<preset>``), frames
    ``skip_frames:skip_frames + max_frames`` after resampling to the options' rate."""
    target_ref = target if isinstance(target, str) and target.startswith("builtin:") else Path(target)
    inputs = JobInputs(Path(motion), target_ref, options=options or RetargetOptions())
    return prepare(inputs, max_frames=max_frames, skip_frames=skip_frames)


def context_from_prepared(prepared: Prepared, device: str = "cpu") -> RefineContext:
    """The refinement context of a prepared job, on ``device``."""
    return refine_context(prepared, prepared.inputs.options.model_copy(update={"device": device}))


def context_from_files(motion_path: str | Path, target: str | Path, start: int = 0, frames: int | None = None,
                       fps: float | None = None) -> RefineContext:  # fmt: skip
    """The context of retargeting frames ``start:start+frames`` (after resampling to ``fps`` when given) of
    ``motion_path`` onto ``target``; ``context.before`` is the copy baseline."""
    prepared = prepared_case(Path(motion_path), target, frames, RetargetOptions(fps=fps), skip_frames=start)
    return refine_context(prepared)


__all__ = ["context_from_files", "context_from_prepared", "prepared_case"]
