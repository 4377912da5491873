"""``/v1/batches``: many motions x many characters in one request, with an aggregate status."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Response
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from api import idempotency
from api.deps import CeleryDep, CurrentKey, MarkerDep, SessionDep, SettingsDep
from api.idempotency import REPLAYED_HEADER, IdempotencyKey, fingerprint
from api.joblife import cancel, queue_webhook, send_webhook
from api.limits import check_active_jobs
from api.models import ApiKey, Batch, Job, new_id
from api.pages import MAX_QUERY_INT, page_bounds
from api.routing import SessionRoute
from api.schemas import BatchCreate, BatchOut, ErrorOut, Page
from api.serialize import batch_out
from api.services.jobs import latest_deliveries, new_job, submit_jobs

router = APIRouter(prefix="/v1/batches", tags=["batches"], route_class=SessionRoute)


def find_batch(session: Session, key: ApiKey, batch_id: str) -> Batch:
    batch = session.get(Batch, batch_id)
    if batch is None or batch.owner_id != key.id:
        raise HTTPException(404, f"batch {batch_id!r} not found")
    return batch


def _out(session: Session, batch: Batch) -> BatchOut:
    jobs = session.scalars(select(Job).where(Job.batch_id == batch.id).order_by(Job.created_at, Job.id)).all()
    return batch_out(batch, jobs, latest_deliveries(session, [j.id for j in jobs]))


@router.post(
    "",
    status_code=202,
    response_model=BatchOut,
    summary="Submit a batch",
    description="Creates one job per (motion, character) pair, motions outer. Every input is checked before "
    "any job is created.",
    responses={422: {"model": ErrorOut}},
)
def create_batch(body: BatchCreate, response: Response, session: SessionDep, key: CurrentKey,
                 settings: SettingsDep, celery: CeleryDep, marker: MarkerDep,
                 idempotency_key: IdempotencyKey = None) -> BatchOut:
    n = len(body.motion_ids) * len(body.target_character_ids)
    if n > settings.max_batch_jobs:
        raise HTTPException(422, f"the batch would create {n} jobs; the limit is {settings.max_batch_jobs} "
                                 "(setting RETARGET_API_MAX_BATCH_JOBS)")
    scope, fp = "POST /v1/batches", fingerprint(body.model_dump_json())
    existing = idempotency.find(session, key.id, idempotency_key, scope, fp)
    if existing:
        response.headers[REPLAYED_HEADER] = "true"
        response.headers["Location"] = f"/v1/batches/{existing}"
        return _out(session, find_batch(session, key, existing))
    check_active_jobs(session, key.id, n, settings)
    batch = Batch(id=new_id("bat"), owner_id=key.id, name=body.name)
    session.add(batch)
    idempotency.remember(session, key.id, idempotency_key, scope, fp, batch.id)
    session.flush()
    jobs = [
        new_job(session, key, settings, m, c, body.source_character_id, body.options, body.callback_url,
                body.queue, batch_id=batch.id)
        for m in body.motion_ids
        for c in body.target_character_ids
    ]
    session.flush()
    submit_jobs(session, celery, jobs, settings.resolved_database_url, marker)
    response.headers["Location"] = f"/v1/batches/{batch.id}"
    return _out(session, batch)


@router.get("", response_model=Page[BatchOut], summary="List batches", description="Newest first.")
def list_batches(
    session: SessionDep,
    key: CurrentKey,
    settings: SettingsDep,
    limit: Annotated[int | None, Query(ge=1, le=MAX_QUERY_INT)] = None,
    offset: Annotated[int, Query(ge=0, le=MAX_QUERY_INT)] = 0,
) -> Page[BatchOut]:
    limit, offset = page_bounds(limit, offset, settings)
    where = Batch.owner_id == key.id
    total = session.scalar(select(func.count()).select_from(Batch).where(where)) or 0
    rows = session.scalars(
        select(Batch).where(where).order_by(Batch.created_at.desc(), Batch.id).limit(limit).offset(offset)
    ).all()
    return Page[BatchOut](items=[_out(session, b) for b in rows], total=total, limit=limit, offset=offset,
                          next_offset=offset + limit if offset + limit < total else None)


@router.get("/{batch_id}", response_model=BatchOut, summary="Get a batch with its jobs",
            responses={404: {"model": ErrorOut}})
def get_batch(batch_id: str, session: SessionDep, key: CurrentKey) -> BatchOut:
    return _out(session, find_batch(session, key, batch_id))


@router.post("/{batch_id}/cancel", response_model=BatchOut, summary="Cancel every unfinished job of a batch",
             responses={404: {"model": ErrorOut}})
def cancel_batch(batch_id: str, session: SessionDep, key: CurrentKey, celery: CeleryDep) -> BatchOut:
    batch = find_batch(session, key, batch_id)
    deliveries = []
    for job in session.scalars(select(Job).where(Job.batch_id == batch.id, Job.status.in_(("queued", "running")))):
        if cancel(session, job) == "canceled":
            deliveries.append(queue_webhook(session, job))
    session.commit()
    for d in deliveries:
        send_webhook(celery, d)
    return _out(session, batch)
