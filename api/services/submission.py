"""``POST /v1/jobs`` and ``GET /v1/jobs/{id}`` on the event loop: the reads, checks and the one write of a
submission through connections no thread shares (a thread hand-off costs a busy loop more than the work), then
the run handed to the outbox."""

from __future__ import annotations

from typing import Any

from fastapi import HTTPException
from sqlalchemy import Row, bindparam, insert, select
from sqlalchemy.engine import Connection
from sqlalchemy.exc import IntegrityError, OperationalError
from starlette.concurrency import run_in_threadpool

from api import idempotency
from api.db import LoopReader, LoopWriter, get_engine, session_scope, write_lock
from api.limits import active_jobs_query, check_job_size, refuse_over_quota
from api.livequeues import waiting_note
from api.models import ApiKey, Asset, IdempotencyRecord, Job, WebhookDelivery, new_id
from api.outbox import SentMarker, submit
from api.schemas import JobCreate, JobOut
from api.serialize import job_out
from api.services.jobs import answer, check_callback, find_job, input_ref, note_for
from api.settings import Settings

_JOBS = Job.__table__
_DELIVERIES = WebhookDelivery.__table__
_ASSETS = Asset.__table__
_IDEM = IdempotencyRecord.__table__
_JOB_BY_ID = select(_JOBS).where(_JOBS.c.id == bindparam("job_id"))
_DELIVERIES_OF_JOB = (select(_DELIVERIES).where(_DELIVERIES.c.job_id == bindparam("job_id"))
                      .order_by(_DELIVERIES.c.created_at))
_IDEM_BY_KEY = select(_IDEM).where(_IDEM.c.owner_id == bindparam("owner_id"), _IDEM.c.key == bindparam("key"))
_INSERT_JOB = insert(Job).returning(*_JOBS.c)
_INSERT_IDEM = insert(IdempotencyRecord)
_INPUTS: dict[int, Any] = {}


def read_job(reader: LoopReader, settings: Settings, key: ApiKey, job_id: str) -> JobOut:
    """A job as GET answers it, read on the event loop as row tuples (no ORM objects, no session)."""
    rows = reader.rows(_JOB_BY_ID, {"job_id": job_id})
    job = rows[0] if rows else None
    if job is None or job.owner_id != key.id:
        raise HTTPException(404, f"job {job_id!r} not found")
    delivery = None
    if job.callback_url:
        deliveries = reader.rows(_DELIVERIES_OF_JOB, {"job_id": job_id})
        delivery = deliveries[-1] if deliveries else None
    note = job.note
    if job.status == "queued" and not note:
        note = waiting_note(job.queue, settings, reader)
    return job_out(job, delivery, note=note)


def _inputs_statement(quota: int) -> Any:
    """The named assets, each row with the key's count of active jobs (at most quota + 1): one round trip."""
    found = _INPUTS.get(quota)
    if found is None:
        active = active_jobs_query(bindparam("owner_id"), quota).scalar_subquery().label("active_jobs")
        found = _INPUTS[quota] = select(_ASSETS, active).where(_ASSETS.c.id.in_(bindparam("ids", expanding=True)))
    return found


def _replayed(reader: LoopReader, settings: Settings, key: ApiKey, idem: str, scope: str, fp: str
              ) -> JobOut | None:
    """The job an earlier request with this Idempotency-Key made; 422 when the key was used for another request."""
    records = reader.rows(_IDEM_BY_KEY, {"owner_id": key.id, "key": idem})
    if not records:
        return None
    record = records[0]
    if record.scope != scope or record.fingerprint != fp:
        raise HTTPException(422, f"the Idempotency-Key {idem[:80]!r} was already used for a different "
                                 f"request ({record.scope}); use a new key for a new request")
    return read_job(reader, settings, key, record.resource_id)


def _checked_inputs(reader: LoopReader, settings: Settings, key: ApiKey, body: JobCreate) -> dict[str, Any]:
    """The inputs' references after the quota, ownership and size checks (one read)."""
    quota = settings.max_active_jobs_per_key
    ids = [i for i in (body.motion_id, body.target_character_id, body.source_character_id) if i]
    rows = reader.rows(_inputs_statement(quota), {"owner_id": key.id, "ids": ids})
    if rows:
        active = int(rows[0].active_jobs or 0)
    else:
        active = int(reader.rows(select(active_jobs_query(key.id, quota).scalar_subquery()))[0][0] or 0)
    refuse_over_quota(active, 1, settings)
    assets = {row.id: row for row in rows}
    motion, target = assets.get(body.motion_id), assets.get(body.target_character_id)
    refs = {"motion_ref": input_ref(motion, key, "motion_id", "motion", body.motion_id),
            "target_ref": input_ref(target, key, "target_character_id", "character", body.target_character_id),
            "source_ref": None}
    if body.source_character_id:
        refs["source_ref"] = input_ref(assets.get(body.source_character_id), key, "source_character_id",
                                       "character", body.source_character_id)
    check_job_size(motion, target, body.options, settings)  # type: ignore[arg-type]
    return refs


def prepare_job(reader: LoopReader, settings: Settings, key: ApiKey, body: JobCreate, idem: str | None,
                scope: str, fp: str) -> tuple[dict[str, Any] | None, JobOut | None]:
    """The reads and checks of a submission, made on the event loop (reads never wait for a lock): the values
    of the job row to insert, or the job an earlier request with the same Idempotency-Key made."""
    if idem:
        replay = _replayed(reader, settings, key, idem, scope, fp)
        if replay is not None:
            return None, replay
    refs = _checked_inputs(reader, settings, key, body)
    return {
        "id": new_id("job"), "owner_id": key.id, "batch_id": None, "motion_id": body.motion_id,
        "target_character_id": body.target_character_id, "source_character_id": body.source_character_id,
        **refs, "options": body.options.model_dump(mode="json"), "queue": body.queue or settings.default_queue,
        "callback_url": check_callback(body.callback_url, settings), "status": "queued", "sent_at": None,
    }, None


def _write_job(conn: Connection, key: ApiKey, values: dict[str, Any], idem: str | None, scope: str,
               fp: str) -> Row[Any]:
    """The write of a submission: the job row and its Idempotency-Key record in one transaction."""
    if idem:
        with conn.begin():
            job = conn.execute(_INSERT_JOB, values).one()
            conn.execute(_INSERT_IDEM, {"owner_id": key.id, "key": idem, "scope": scope, "fingerprint": fp,
                                        "resource_id": job.id})
        return job
    # one statement: autocommit spares PostgreSQL's BEGIN and COMMIT round trips
    return conn.execution_options(isolation_level="AUTOCOMMIT").execute(_INSERT_JOB, values).one()


def _write_job_in_thread(url: str, key: ApiKey, values: dict[str, Any], idem: str | None, scope: str,
                         fp: str) -> Row[Any]:
    """:func:`_write_job` through the pool, taking turns with this process's other writers (SQLite)."""
    with write_lock(url), get_engine(url).connect() as conn:
        return _write_job(conn, key, values, idem, scope, fp)


def _replay_race(settings: Settings, key: ApiKey, idem: str | None, scope: str, fp: str,
                 error: IntegrityError) -> JobOut:
    """After an IntegrityError: the job a concurrent request with the same Idempotency-Key made."""
    if not idem:
        raise error
    with session_scope(settings.resolved_database_url) as s:
        existing = idempotency.find(s, key.id, idem, scope, fp)
        if existing is None:
            raise error
        return answer(s, find_job(s, key, existing), settings)


async def insert_job(state: Any, settings: Settings, celery: Any, key: ApiKey, values: dict[str, Any],
                     idem: str | None, scope: str, fp: str) -> tuple[JobOut, bool]:
    """Write the job on the event loop (in a thread when the loop's write would have to wait), then hand its run
    to the outbox. Returns the job and whether it is a concurrent request's (same Idempotency-Key)."""
    url = settings.resolved_database_url
    writer: LoopWriter = state.loop_writer
    try:
        try:
            with writer.connect() as conn:
                job = _write_job(conn, key, values, idem, scope, fp)
        except OperationalError as exc:  # busy, a lock timeout, a broken connection: nothing was written
            if exc.connection_invalidated:
                writer.close()
            job = await run_in_threadpool(_write_job_in_thread, url, key, values, idem, scope, fp)
    except IntegrityError as exc:
        return await run_in_threadpool(_replay_race, settings, key, idem, scope, fp, exc), True
    runs = [(job.id, job.attempt, job.queue)]
    marker: SentMarker | None = getattr(state, "sent_marker", None)
    if marker is not None:
        submit(url, celery, runs, marker)
    else:
        await run_in_threadpool(submit, url, celery, runs)
    return job_out(job, None, note=note_for(job, settings, state.loop_reader)), False
