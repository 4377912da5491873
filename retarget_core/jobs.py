"""The contract between the service and the library: what one job takes and gives back.

Light on purpose (no torch): the API imports these types; only the worker runs :func:`retarget_core.pipeline.run_job`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from retarget_core.options import RetargetOptions

ProgressCallback = Callable[[str, float], None]
"""Called with (stage name, fraction of the whole job done in 0..1)."""

CancelCheck = Callable[[], bool]
"""Returns True when the job should stop; the pipeline then raises :class:`JobCanceled` between stages."""


class JobCanceled(Exception):
    """Raised by the pipeline when its cancel check returns True."""


@dataclass
class JobInputs:
    """Files of one job. The target is a file or a built-in body name (``builtin:<preset>``)."""

    motion_path: Path
    target: Path | str
    source_character: Path | str | None = None
    options: RetargetOptions = field(default_factory=RetargetOptions)


OUTPUT_FILES: dict[str, str] = {
    "result_glb": "result.glb",
    "before_glb": "before.glb",
    "source_glb": "source.glb",
    "metrics_json": "metrics.json",
}
"""The files of a finished job, by :class:`JobOutputs` field: the one place they are named."""


@dataclass
class JobOutputs:
    """What a finished job wrote into its output directory."""

    result_glb: Path
    before_glb: Path
    metrics_json: Path
    summary: dict[str, Any]
    stage_seconds: dict[str, float]
    warnings: list[str]
    source_glb: Path | None = None
    """The source motion on the source body (its own mesh, the one given, or a built-in body sized to it)."""
