"""Rows to response bodies (shared by the API and the worker's webhook payloads)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import Any

from sqlalchemy import Row

from api.models import Asset, Batch, Job, WebhookDelivery
from api.schemas import FINISHED, AssetOut, BatchOut, JobOut, Timings, WebhookState
from retarget_core.jobs import OUTPUT_FILES

_CONTENT_TYPES = {".glb": "model/gltf-binary", ".json": "application/json"}
RESULT_FILES: dict[str, tuple[str, str]] = {
    # file name in the URL -> (key in JobOut.results, content type); the names come from the library
    name: (key, _CONTENT_TYPES[name[name.rindex("."):]]) for key, name in OUTPUT_FILES.items()
}

ASSET_CONTENT_TYPES = {
    "glb": "model/gltf-binary",
    "gltf": "model/gltf+json",
    "bvh": "application/octet-stream",
    "fbx": "application/octet-stream",
}


def collection(kind: str) -> str:
    """URL collection of an asset kind."""
    return "characters" if kind == "character" else "motions"


def asset_out(asset: Asset, base: str = "") -> AssetOut:
    """The public view of an asset row."""
    self_url = f"{base}/v1/{collection(asset.kind)}/{asset.id}"
    links = {"self": self_url}
    if asset.sha256:
        links["file"] = f"{self_url}/file"
    return AssetOut(
        id=asset.id,
        kind=asset.kind,
        name=asset.name,
        builtin=asset.origin == "builtin",
        origin=asset.origin,
        filename=asset.filename,
        format=asset.format,
        size_bytes=asset.size_bytes,
        sha256=asset.sha256,
        created_at=asset.created_at,
        info=asset.info or {},
        params=asset.params,
        links=links,
    )


def job_out(job: Job | Row[Any], delivery: WebhookDelivery | Row[Any] | None = None, base: str = "",
            note: str | None = None) -> JobOut:
    """The public view of a job row (an ORM object or a row of the jobs table, with its newest webhook delivery);
    ``note`` replaces the row's own note (e.g. no worker serves its queue)."""
    url = f"{base}/v1/jobs/{job.id}"
    results = None
    if job.status == "succeeded" and job.outputs:
        results = {RESULT_FILES[name][0]: f"{url}/{name}" for name in RESULT_FILES if name in job.outputs}
    queued = run = None
    if job.started_at is not None:
        queued = max(0.0, (job.started_at - (job.sent_at or job.created_at)).total_seconds())
        if job.finished_at is not None and job.status != "queued":
            run = max(0.0, (job.finished_at - job.started_at).total_seconds())
    links = {"self": url, "motion": f"{base}/v1/motions/{job.motion_id}",
             "target_character": f"{base}/v1/characters/{job.target_character_id}"}
    if job.status not in FINISHED:
        links["cancel"] = f"{url}/cancel"
    if job.status in ("failed", "canceled"):
        links["retry"] = f"{url}/retry"
    if job.batch_id:
        links["batch"] = f"{base}/v1/batches/{job.batch_id}"
    webhook = None
    if delivery is not None:
        webhook = WebhookState(
            event=delivery.event,
            status=delivery.status,
            attempts=delivery.attempts,
            last_status_code=delivery.last_status_code,
            last_error=delivery.last_error,
        )
    return JobOut(
        id=job.id,
        status=job.status,
        stage=job.stage,
        progress=min(1.0, max(0.0, job.progress or 0.0)),
        message=job.message,
        note=note or job.note,
        error_kind=job.error_kind,
        cancel_requested=job.cancel_requested,
        attempt=job.attempt,
        batch_id=job.batch_id,
        motion_id=job.motion_id,
        target_character_id=job.target_character_id,
        source_character_id=job.source_character_id,
        options=job.options or {},
        queue=job.queue,
        callback_url=job.callback_url,
        worker=job.worker,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        updated_at=job.updated_at,
        timings=Timings(queued_seconds=queued, run_seconds=run, stages=job.stage_seconds or {}),
        summary=job.summary,
        warnings=[str(w) for w in (job.warnings or [])],
        results=results,
        webhook=webhook,
        links=links,
    )


def batch_status(statuses: Sequence[str]) -> str:
    """The aggregate status of a batch from its jobs' statuses."""
    counts = Counter(statuses)
    if not statuses or counts["queued"] == len(statuses):
        return "queued"
    if any(s not in FINISHED for s in statuses):
        return "running"
    if counts["succeeded"] == len(statuses):
        return "succeeded"
    if counts["failed"]:
        return "failed"
    return "canceled"


def batch_out(batch: Batch, jobs: Sequence[Job], deliveries: dict[str, WebhookDelivery], base: str = "") -> BatchOut:
    """The public view of a batch and its jobs."""
    statuses = [j.status for j in jobs]
    counts = {s: 0 for s in ("queued", "running", "succeeded", "failed", "canceled")}
    counts.update(Counter(statuses))
    progress = sum(1.0 if j.status in FINISHED else (j.progress or 0.0) for j in jobs) / max(1, len(jobs))
    url = f"{base}/v1/batches/{batch.id}"
    return BatchOut(
        id=batch.id,
        name=batch.name,
        created_at=batch.created_at,
        status=batch_status(statuses),
        total=len(jobs),
        counts=counts,
        progress=progress,
        jobs=[job_out(j, deliveries.get(j.id), base) for j in jobs],
        links={"self": url, "cancel": f"{url}/cancel", "jobs": f"{base}/v1/jobs?batch_id={batch.id}"},
    )


def webhook_payload(job: Job, delivery: WebhookDelivery, base: str = "") -> dict[str, object]:
    """The JSON body POSTed to a job's callback URL."""
    return {
        "event": delivery.event,
        "delivery_id": delivery.id,
        "job": job_out(job, None, base).model_dump(mode="json"),
    }
