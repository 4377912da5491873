"""A :class:`RefineContext` built from a motion file and a target without running any stage (tests,
benchmarks, stage development): exactly what the pipeline gives the stages (:func:`pipeline.prepare`)."""

from __future__ import annotations

from pathlib import Path

from retarget_core.jobs import JobInputs
from retarget_core.options import RetargetOptions
from retarget_core.refine.context import RefineContext


def context_from_files(motion_path: str | Path, target: str | Path, start: int = 0, frames: int | None = None,
                       fps: float | None = None) -> RefineContext:  # fmt: skip
    """The context of retargeting frames ``start:start+frames`` (after resampling to ``fps`` when given) of
    ``motion_path`` onto ``target`` (a file or ``builtin:<preset>``); ``context.before`` is the copy baseline."""
    from retarget_core.pipeline import prepare, refine_context

    target_ref = target if isinstance(target, str) and target.startswith("builtin:") else Path(target)
    prepared = prepare(JobInputs(Path(motion_path), target_ref, options=RetargetOptions(fps=fps)),
                       max_frames=frames, skip_frames=start)  # fmt: skip
    return refine_context(prepared)


__all__ = ["context_from_files"]
