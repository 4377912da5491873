"""The metrics JSON of a job: what was read, what ran, and the quality numbers of before and after."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from retarget_core.pipeline import Retargeted

SCHEMA_VERSION = "0.1"


def build_metrics(result: Retargeted) -> dict[str, Any]:
    """A JSON-ready dict describing a retarget job (see docs/metrics.md)."""
    src, tgt = result.source, result.target
    motion = src.motion
    return {
        "schema_version": SCHEMA_VERSION,
        "source": {
            "name": motion.name,
            "format": src.format,
            "frames": motion.num_frames,
            "fps": motion.fps,
            "duration_s": motion.duration,
            "joints": motion.skeleton.num_joints,
            "mapping": src.mapping.report(motion.skeleton.names),
            "normalization": src.normalization.as_dict(),
        },
        "target": {
            "name": tgt.character.name,
            "format": tgt.format,
            "height_m": tgt.character.height,
            "vertices": tgt.character.num_vertices,
            "joints": tgt.character.skeleton.num_joints,
            "mapping": tgt.mapping.report(tgt.character.skeleton.names),
            "normalization": tgt.normalization.as_dict(),
        },
        "stages_run": result.stages_run,
        "stages_skipped": result.stages_skipped,
        "warnings": result.warnings,
        "summary": {},
    }
