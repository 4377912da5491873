"""The metrics JSON of a job: the quality numbers of before and after (``retarget_core.metrics``, schema in
docs/metrics.md) with what was read and what ran in ``context``."""

from __future__ import annotations

from typing import Any

from retarget_core.measure import measure_job
from retarget_core.retargeted import Retargeted


def job_context(result: Retargeted) -> dict[str, Any]:
    """What the pipeline read and did: inputs, joint mappings, normalisation, stages, warnings."""
    src, tgt, body = result.source, result.target, result.source_body
    motion = src.motion
    return {
        "source": {
            "name": motion.name,
            "format": src.format,
            "frames": motion.num_frames,
            "fps": motion.fps,
            "duration_s": motion.duration,
            "joints": motion.skeleton.num_joints,
            "mapping": src.mapping.report(motion.skeleton.names),
            "normalization": src.normalization.as_dict(),
            "body": body.character.name,
            "body_height_m": round(body.character.height, 4),
        },
        "target": {
            "name": tgt.character.name,
            "format": tgt.format,
            "height_m": round(tgt.character.height, 4),
            "vertices": tgt.character.num_vertices,
            "joints": tgt.character.skeleton.num_joints,
            "mapping": tgt.mapping.report(tgt.character.skeleton.names),
            "normalization": tgt.normalization.as_dict(),
        },
        "stages_run": result.stages_run,
        "stages_skipped": result.stages_skipped,
        "stage_reports": result.stage_reports,
        "body_cache": "hit" if result.prepared.body_cached else "built",
        "warnings": result.warnings,
    }


def build_metrics(result: Retargeted, include_series: bool = True) -> dict[str, Any]:
    """The job's metrics JSON as a dict: contacts detected on the source, carried to the target, and the metrics
    of "before" (copy baseline) and "after" (the result) on the target."""
    p = result.prepared
    measured = measure_job(
        p.source_body.character, p.source_body.mapping, p.source_view, p.target.character, p.target.mapping,
        p.before, result.after, source_contacts=p.contacts, constraints=p.constraints,
        context=job_context(result), notes=list(result.warnings), include_series=include_series, threads=None,
    )  # fmt: skip
    # What came in broken joins the job's warnings (JobOutputs.warnings is this list).
    source = measured.report.source
    result.warnings.extend(w for w in (source.warnings if source else []) if w not in result.warnings)
    report: dict[str, Any] = measured.report.model_dump(mode="json")
    return report


def headline(report: dict[str, Any]) -> dict[str, Any]:
    """The few numbers a job listing shows: before/after summaries and the improvement."""
    return {
        "before": (report.get("before") or {}).get("summary"),
        "after": (report.get("after") or {}).get("summary"),
        "improvement": report.get("improvement"),
    }
