"""Refinement stages: each turns the motion so far into a better one on the target. One module per stage,
registered here in the pipeline's order (:data:`retarget_core.stages.STAGES`); the pipeline runs
:func:`refinement_stages` and nothing else knows the order.

To add a stage: write ``refine/<name>.py`` with ``run(context, motion) -> StageOutcome``, add its
:class:`~retarget_core.stages.StageInfo` to ``stages.STAGES`` and its loader to :data:`_LOADERS`.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module

from retarget_core.refine.context import RefineContext, RefineStage, StageOutcome, resolve_device
from retarget_core.stages import REFINEMENT_STAGE_NAMES, StageInfo, stage_info

# Stage name -> module whose ``run`` implements it (imported when first used).
_MODULES: dict[str, str] = {
    "recurrent": "retarget_core.refine.recurrent",
    "eso": "retarget_core.refine.eso",
    "learned_collisions": "retarget_core.refine.collision_model",
    "collisions": "retarget_core.refine.collisions",
    "foot_lock": "retarget_core.refine.foot_lock",
}


def load_stage(name: str) -> RefineStage:
    """The ``run`` function of refinement stage ``name``."""
    fn: Callable[..., StageOutcome] = import_module(_MODULES[name]).run
    return fn


def refinement_stages() -> list[tuple[StageInfo, RefineStage | None]]:
    """Every refinement stage in order, with its function (None when not available in this version)."""
    out: list[tuple[StageInfo, RefineStage | None]] = []
    for name in REFINEMENT_STAGE_NAMES:
        info = stage_info(name)
        out.append((info, load_stage(name) if info.available else None))
    return out


__all__ = ["RefineContext", "RefineStage", "StageOutcome", "load_stage", "refinement_stages", "resolve_device"]
