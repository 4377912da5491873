"""Refinement stages: each turns the motion so far into a better one on the target. One module per stage,
registered here in the pipeline's order (:data:`retarget_core.stages.STAGES`); the pipeline runs
:func:`refinement_stages` and nothing else knows the order.

To add a stage: write ``refine/<name>.py`` with ``run(context, motion) -> StageOutcome`` and add its
:class:`~retarget_core.stages.StageInfo` (which names the module) to ``stages.STAGES``.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module

from retarget_core.context import RefineContext, RefineStage, StageOutcome, resolve_device
from retarget_core.stages import REFINEMENT_STAGE_NAMES, StageInfo, stage_info


def load_stage(name: str) -> RefineStage:
    """The ``run`` function of refinement stage ``name``."""
    module = stage_info(name).module
    if module is None:
        raise KeyError(f"{name} is not a refinement stage")
    fn: Callable[..., StageOutcome] = import_module(module).run
    return fn


def refinement_stages() -> list[tuple[StageInfo, RefineStage | None]]:
    """Every refinement stage in order, with its function (None when not available in this version)."""
    out: list[tuple[StageInfo, RefineStage | None]] = []
    for name in REFINEMENT_STAGE_NAMES:
        info = stage_info(name)
        out.append((info, load_stage(name) if info.available else None))
    return out


__all__ = ["RefineContext", "RefineStage", "StageOutcome", "load_stage", "refinement_stages", "resolve_device"]
