"""Jobs: find, create (checked rows), submit through the outbox, cancel, retry, answer, and their result files."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import HTTPException
from sqlalchemy import Row, select
from sqlalchemy.orm import Session

from api import idempotency
from api.callbacks import CallbackRefused, check_url
from api.db import LoopReader
from api.joblife import cancel, queue_webhook, retry, send_webhook
from api.limits import check_job_size
from api.livequeues import waiting_note
from api.models import ApiKey, Asset, Job, WebhookDelivery, new_id
from api.outbox import SentMarker, submit
from api.schemas import JobOut
from api.serialize import RESULT_FILES, job_out
from api.settings import Settings
from api.storage import Storage
from retarget_core.options import RetargetOptions


def find_job(session: Session, key: ApiKey, job_id: str) -> Job:
    """The job ``job_id`` of ``key``; 404 otherwise."""
    job = session.get(Job, job_id)
    if job is None or job.owner_id != key.id:
        raise HTTPException(404, f"job {job_id!r} not found")
    return job


def input_ref(asset: Asset | Row[Any] | None, key: ApiKey, field: str, kind: str, asset_id: str) -> str:
    """The reference the worker reads for an asset (an ORM object or a row); 422 when it is not usable."""
    if asset is None or asset.kind != kind or (asset.owner_id != key.id and asset.origin != "builtin"):
        raise HTTPException(422, f"{field}: no {kind} with id {asset_id!r}")
    if asset.origin == "builtin":
        preset = (asset.params or {}).get("preset") or asset.id.removeprefix("builtin:")
        return f"builtin:{preset}"
    if not asset.sha256 or not asset.format:
        raise HTTPException(422, f"{field}: {kind} {asset_id!r} has no file")
    return Storage.blob_ref(asset.sha256, asset.format)


def resolve_input(session: Session, key: ApiKey, field: str, kind: str, asset_id: str) -> tuple[Asset, str]:
    """The asset named in a request field and the reference the worker reads; 422 when it is not usable."""
    asset = session.get(Asset, asset_id)
    return asset, input_ref(asset, key, field, kind, asset_id)  # type: ignore[return-value]


def check_callback(callback_url: Any, settings: Settings) -> str | None:
    """The callback URL as text when a job may name it; 422 with the reason otherwise."""
    if not callback_url:
        return None
    try:
        return check_url(str(callback_url), settings.callback_allowed_hosts, settings.max_callback_url_length)
    except CallbackRefused as exc:
        raise HTTPException(422, str(exc)) from exc


def new_job(session: Session, key: ApiKey, settings: Settings, motion_id: str, target_id: str,
            source_id: str | None, options: RetargetOptions, callback_url: Any, queue: str | None,
            batch_id: str | None = None) -> Job:
    """A queued job row (not yet sent: ``sent_at`` is set once the broker took its message) after checking its
    inputs, its size and its callback URL."""
    motion, motion_ref = resolve_input(session, key, "motion_id", "motion", motion_id)
    target, target_ref = resolve_input(session, key, "target_character_id", "character", target_id)
    source_ref = None
    if source_id:
        _, source_ref = resolve_input(session, key, "source_character_id", "character", source_id)
    check_job_size(motion, target, options, settings)
    job = Job(
        id=new_id("job"), owner_id=key.id, batch_id=batch_id, motion_id=motion_id, target_character_id=target_id,
        source_character_id=source_id, motion_ref=motion_ref, target_ref=target_ref, source_ref=source_ref,
        options=options.model_dump(mode="json"), queue=queue or settings.default_queue,
        callback_url=check_callback(callback_url, settings), status="queued", sent_at=None,
    )
    session.add(job)
    return job


def submit_jobs(session: Session, celery: Any, jobs: list[Job], url: str, marker: SentMarker | None) -> None:
    """Commit the rows, then hand their runs to the outbox (the one way a job is sent)."""
    session.commit()
    submit(url, celery, [(job.id, job.attempt, job.queue) for job in jobs], marker)


def latest_deliveries(session: Session, job_ids: list[str]) -> dict[str, WebhookDelivery]:
    """The newest webhook delivery of each job."""
    if not job_ids:
        return {}
    rows = session.scalars(
        select(WebhookDelivery).where(WebhookDelivery.job_id.in_(job_ids)).order_by(WebhookDelivery.created_at)
    ).all()
    return {d.job_id: d for d in rows}


def note_for(job: Job | Row[Any], settings: Settings, reader: LoopReader | None = None) -> str | None:
    """The job's note, or for a queued job on a queue no live worker serves, a note saying so (the queues read
    through ``reader`` when given)."""
    if job.status == "queued" and not job.note:
        return waiting_note(job.queue, settings, reader)
    return job.note


def answer(session: Session, job: Job, settings: Settings) -> JobOut:
    """The job as the API shows it (with its newest webhook delivery and its note)."""
    delivery = latest_deliveries(session, [job.id]).get(job.id) if job.callback_url else None
    return job_out(job, delivery, note=note_for(job, settings))


def cancel_job(session: Session, celery: Any, key: ApiKey, job_id: str) -> Job:
    """Cancel (or ask to stop) a job; 409 when it has finished. Its webhook is sent after the commit."""
    job = find_job(session, key, job_id)
    result = cancel(session, job)
    if result == "finished":
        raise HTTPException(409, f"job {job_id!r} has already finished ({job.status})")
    delivery = queue_webhook(session, job) if result == "canceled" else None
    session.commit()
    send_webhook(celery, delivery)
    return job


def retry_job(session: Session, celery: Any, key: ApiKey, job_id: str, idem: str | None, url: str,
              marker: SentMarker | None) -> tuple[Job, bool]:
    """Queue a failed or canceled job again and submit it; 409 otherwise. Returns it and whether the request
    is a replay of an earlier one with the same Idempotency-Key."""
    job = find_job(session, key, job_id)
    scope, fp = "POST /v1/jobs/{id}/retry", idempotency.fingerprint(job_id)
    if idempotency.find(session, key.id, idem, scope, fp):
        return job, True
    if not retry(session, job):
        raise HTTPException(409, f"only failed or canceled jobs can be retried; job {job_id!r} is {job.status}")
    idempotency.remember(session, key.id, idem, scope, fp, job.id)
    submit_jobs(session, celery, [job], url, marker)
    return job, False


def result_path(session: Session, key: ApiKey, storage: Storage, job_id: str, name: str) -> Path:
    """Where a result file of a succeeded job is; 409 before it succeeded, 404 when the file is not there."""
    job = find_job(session, key, job_id)
    if job.status != "succeeded":
        raise HTTPException(409, f"job {job_id!r} is {job.status}; results are there once it has succeeded")
    rel = (job.outputs or {}).get(name)
    if not rel:
        raise HTTPException(404, f"job {job_id!r} has no {name}")
    path = storage.resolve(rel)
    if not path.is_file():
        raise HTTPException(404, f"{name} of job {job_id!r} is missing from storage")
    return path


def result_media_type(name: str) -> str:
    return RESULT_FILES[name][1]
