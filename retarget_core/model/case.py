"""A :class:`RefineContext` for one motion x target outside a job (tests, benchmarks, the evaluation of the
network), built from :func:`retarget_core.pipeline.prepare` the way :func:`retarget_core.pipeline.refine` does."""

from __future__ import annotations

from pathlib import Path

import torch

from retarget_core.jobs import JobInputs
from retarget_core.options import RetargetOptions
from retarget_core.refine.context import RefineContext
from retarget_core.retargeted import Prepared


def prepared_case(motion: Path, target: Path | str, max_frames: int | None = None, options: RetargetOptions | None = None) -> Prepared:
    """Everything up to the copy baseline for ``motion`` on ``target`` (first ``max_frames`` frames)."""
    from retarget_core.pipeline import prepare

    return prepare(JobInputs(Path(motion), target, options=options or RetargetOptions()), max_frames=max_frames)


def context_from_prepared(prepared: Prepared, device: str = "cpu") -> RefineContext:
    """The refinement context of a prepared job (same fields as the pipeline fills)."""
    return RefineContext(
        target=prepared.target.character, target_mapping=prepared.target.mapping,
        parts=prepared.assets.parts, sdf=prepared.assets.sdf,
        source_body=prepared.source_body.character, source_mapping=prepared.source_body.mapping,
        source_view=prepared.source_view, self_contacts=prepared.contacts.self_contacts,
        constraints=prepared.constraints, feet=prepared.target_feet, before=prepared.before,
        options=prepared.inputs.options, device=torch.device(device),
    )  # fmt: skip


__all__ = ["context_from_prepared", "prepared_case"]
