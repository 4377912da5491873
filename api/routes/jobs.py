"""``/v1/jobs``: submit, list, get, cancel, retry, and download results."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel
from sqlalchemy import Row, bindparam, func, insert, select
from sqlalchemy.engine import Connection
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from api import idempotency
from api.callbacks import CallbackRefused, check_url
from api.db import LoopReader, LoopWriter, get_engine, session_scope, write_lock
from api.deps import CeleryDep, CurrentKey, SessionDep, SettingsDep, StorageDep
from api.idempotency import REPLAYED_HEADER, IdempotencyKey, fingerprint
from api.joblife import cancel, queue_webhook, retry, send_and_mark, send_webhook
from api.limits import active_jobs_query, check_job_size, refuse_over_quota
from api.livequeues import waiting_note
from api.models import ApiKey, Asset, IdempotencyRecord, Job, WebhookDelivery, new_id
from api.pages import MAX_QUERY_INT, page_bounds
from api.routing import SessionRoute
from api.schemas import ErrorOut, JobCreate, JobOut, JobStatus, Page
from api.sentmarks import SentMarker
from api.serialize import RESULT_FILES, job_out
from api.settings import Settings
from api.storage import Storage
from retarget_core.options import RetargetOptions

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=SessionRoute)

_JOBS = Job.__table__
_DELIVERIES = WebhookDelivery.__table__
_JOB_BY_ID = select(_JOBS).where(_JOBS.c.id == bindparam("job_id"))
_DELIVERIES_OF_JOB = (select(_DELIVERIES).where(_DELIVERIES.c.job_id == bindparam("job_id"))
                      .order_by(_DELIVERIES.c.created_at))


def resolve_input(session: Session, key: ApiKey, field: str, kind: str, asset_id: str) -> tuple[Asset, str]:
    """The asset named in a request field and the reference the worker reads; 422 when it is not usable."""
    asset = session.get(Asset, asset_id)
    return asset, input_ref(asset, key, field, kind, asset_id)  # type: ignore[return-value]


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


def dispatch(session: Session, celery: Any, jobs: list[Job], url: str, marker: SentMarker | None = None) -> None:
    """Commit the rows, then send them and record that they were sent."""
    session.commit()
    send_and_mark(url, celery, [(job.id, job.attempt, job.queue) for job in jobs], marker)


def find_job(session: Session, key: ApiKey, job_id: str) -> Job:
    job = session.get(Job, job_id)
    if job is None or job.owner_id != key.id:
        raise HTTPException(404, f"job {job_id!r} not found")
    return job


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


def out(session: Session, job: Job, settings: Settings) -> JobOut:
    delivery = latest_deliveries(session, [job.id]).get(job.id) if job.callback_url else None
    return job_out(job, delivery, note=note_for(job, settings))


def json_response(model: BaseModel, status_code: int = 200, headers: dict[str, str] | None = None) -> Response:
    """A response body already validated by its model (FastAPI would validate it again, in another thread)."""
    return Response(model.model_dump_json(), status_code=status_code, media_type="application/json",
                    headers=headers)


def _replay_race(settings: Settings, key: ApiKey, idem: str | None, scope: str, fp: str,
                 error: IntegrityError) -> JobOut:
    """After an IntegrityError: the job a concurrent request with the same Idempotency-Key made."""
    if not idem:
        raise error
    with session_scope(settings.resolved_database_url) as s:
        existing = idempotency.find(s, key.id, idem, scope, fp)
        if existing is None:
            raise error
        return out(s, find_job(s, key, existing), settings)


_ASSETS = Asset.__table__
_IDEM = IdempotencyRecord.__table__
_IDEM_BY_KEY = select(_IDEM).where(_IDEM.c.owner_id == bindparam("owner_id"), _IDEM.c.key == bindparam("key"))
_INSERT_JOB = insert(Job).returning(*_JOBS.c)
_INSERT_IDEM = insert(IdempotencyRecord)
_INPUTS: dict[int, Any] = {}


def _inputs_statement(quota: int) -> Any:
    """The named assets, each row with the key's count of active jobs (at most quota + 1): one round trip."""
    found = _INPUTS.get(quota)
    if found is None:
        active = active_jobs_query(bindparam("owner_id"), quota).scalar_subquery().label("active_jobs")
        found = _INPUTS[quota] = select(_ASSETS, active).where(_ASSETS.c.id.in_(bindparam("ids", expanding=True)))
    return found


def _prepare_job(reader: LoopReader, settings: Settings, key: ApiKey, body: JobCreate, idem: str | None,
                 scope: str, fp: str) -> tuple[dict[str, Any] | None, JobOut | None]:
    """The reads and checks of a submission, made on the event loop (reads never wait for a lock): the values
    of the job row to insert, or the job an earlier request with the same Idempotency-Key made."""
    if idem:
        records = reader.rows(_IDEM_BY_KEY, {"owner_id": key.id, "key": idem})
        if records:
            record = records[0]
            if record.scope != scope or record.fingerprint != fp:
                raise HTTPException(422, f"the Idempotency-Key {idem[:80]!r} was already used for a different "
                                         f"request ({record.scope}); use a new key for a new request")
            return None, read_job(reader, settings, key, record.resource_id)
    quota = settings.max_active_jobs_per_key
    ids = [i for i in (body.motion_id, body.target_character_id, body.source_character_id) if i]
    rows = reader.rows(_inputs_statement(quota), {"owner_id": key.id, "ids": ids})
    if rows:
        active = int(rows[0].active_jobs or 0)
    else:
        active = int(reader.rows(select(active_jobs_query(key.id, quota).scalar_subquery()))[0][0] or 0)
    refuse_over_quota(active, 1, settings)
    assets = {row.id: row for row in rows}
    motion = assets.get(body.motion_id)
    target = assets.get(body.target_character_id)
    motion_ref = input_ref(motion, key, "motion_id", "motion", body.motion_id)
    target_ref = input_ref(target, key, "target_character_id", "character", body.target_character_id)
    source_ref = None
    if body.source_character_id:
        source_ref = input_ref(assets.get(body.source_character_id), key, "source_character_id", "character",
                               body.source_character_id)
    check_job_size(motion, target, body.options, settings)  # type: ignore[arg-type]
    return {
        "id": new_id("job"), "owner_id": key.id, "batch_id": None, "motion_id": body.motion_id,
        "target_character_id": body.target_character_id, "source_character_id": body.source_character_id,
        "motion_ref": motion_ref, "target_ref": target_ref, "source_ref": source_ref,
        "options": body.options.model_dump(mode="json"), "queue": body.queue or settings.default_queue,
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


async def _insert_job(state: Any, settings: Settings, celery: Any, key: ApiKey, values: dict[str, Any],
                      idem: str | None, scope: str, fp: str) -> tuple[JobOut, bool]:
    """Write the job on the event loop (in a thread when the loop's write would have to wait), then send it:
    from the marker's thread when there is one (the committed row is the outbox), else in a thread now."""
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
        marker.send(celery, runs)
    else:
        await run_in_threadpool(send_and_mark, url, celery, runs)
    return job_out(job, None, note=note_for(job, settings, state.loop_reader)), False


@router.post(
    "",
    status_code=202,
    response_model=JobOut,
    summary="Submit a job",
    description="Queue one motion on one target character. Answers 202 at once with the job (Location header "
    "and links.self point at it); poll it or pass a callback_url. With an Idempotency-Key header, a repeated "
    "request answers with the job the first one made.",
    responses={422: {"model": ErrorOut, "description": "An input does not exist, the options are invalid or the "
                     "job is over a size limit"},
               429: {"model": ErrorOut, "description": "Over the key's quota of queued and running jobs"}},
)
async def create_job(request: Request, body: JobCreate, key: CurrentKey, settings: SettingsDep, celery: CeleryDep,
                     idempotency_key: IdempotencyKey = None) -> Response:
    # Reads, checks and the write on the event loop; the send from the marker's thread.
    scope, fp = "POST /v1/jobs", fingerprint(body.model_dump_json())
    values, replay = _prepare_job(request.app.state.loop_reader, settings, key, body, idempotency_key, scope, fp)
    if values is None:
        assert replay is not None
        job, replayed = replay, True
    else:
        job, replayed = await _insert_job(request.app.state, settings, celery, key, values, idempotency_key,
                                          scope, fp)
    headers = {"Location": f"/v1/jobs/{job.id}"}
    if replayed:
        headers[REPLAYED_HEADER] = "true"
    return json_response(job, 202, headers)


@router.get("", response_model=Page[JobOut], summary="List jobs", description="Newest first.")
def list_jobs(
    session: SessionDep,
    key: CurrentKey,
    settings: SettingsDep,
    status: Annotated[JobStatus | None, Query(description="Only jobs in this state")] = None,
    batch_id: Annotated[str | None, Query(description="Only jobs of this batch")] = None,
    limit: Annotated[int | None, Query(ge=1, le=MAX_QUERY_INT)] = None,
    offset: Annotated[int, Query(ge=0, le=MAX_QUERY_INT)] = 0,
) -> Page[JobOut]:
    limit, offset = page_bounds(limit, offset, settings)
    where = [Job.owner_id == key.id]
    if status:
        where.append(Job.status == status)
    if batch_id:
        where.append(Job.batch_id == batch_id)
    total = session.scalar(select(func.count()).select_from(Job).where(*where)) or 0
    rows = session.scalars(
        select(Job).where(*where).order_by(Job.created_at.desc(), Job.id).limit(limit).offset(offset)
    ).all()
    deliveries = latest_deliveries(session, [j.id for j in rows])
    return Page[JobOut](
        items=[job_out(j, deliveries.get(j.id), note=note_for(j, settings)) for j in rows], total=total,
        limit=limit, offset=offset,
        next_offset=offset + limit if offset + limit < total else None,
    )




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


@router.get("/{job_id}", response_model=JobOut, summary="Get a job", responses={404: {"model": ErrorOut}})
async def get_job(request: Request, job_id: str, key: CurrentKey) -> Response:
    state = request.app.state
    return json_response(read_job(state.loop_reader, state.settings, key, job_id))


@router.post(
    "/{job_id}/cancel",
    response_model=JobOut,
    summary="Cancel a job",
    description="A queued job is canceled at once. A running job gets cancel_requested and stops at the next "
    "stage boundary (its status turns canceled then). A finished job answers 409.",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
def cancel_job(job_id: str, session: SessionDep, key: CurrentKey, celery: CeleryDep, settings: SettingsDep) -> JobOut:
    job = find_job(session, key, job_id)
    result = cancel(session, job)
    if result == "finished":
        raise HTTPException(409, f"job {job_id!r} has already finished ({job.status})")
    delivery = queue_webhook(session, job) if result == "canceled" else None
    session.commit()
    send_webhook(celery, delivery)
    return out(session, job, settings)


@router.post(
    "/{job_id}/retry",
    response_model=JobOut,
    status_code=202,
    summary="Run a failed or canceled job again",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
def retry_job(job_id: str, response: Response, session: SessionDep, key: CurrentKey, celery: CeleryDep,
              settings: SettingsDep, idempotency_key: IdempotencyKey = None) -> JobOut:
    job = find_job(session, key, job_id)
    scope, fp = "POST /v1/jobs/{id}/retry", fingerprint(job_id)
    if idempotency.find(session, key.id, idempotency_key, scope, fp):
        response.headers[REPLAYED_HEADER] = "true"
        return out(session, job, settings)
    if not retry(session, job):
        raise HTTPException(409, f"only failed or canceled jobs can be retried; job {job_id!r} is {job.status}")
    idempotency.remember(session, key.id, idempotency_key, scope, fp, job.id)
    dispatch(session, celery, [job], settings.resolved_database_url)
    return out(session, job, settings)


def _result(job_id: str, name: str, session: Session, key: ApiKey, storage: Storage) -> FileResponse:
    job = find_job(session, key, job_id)
    if job.status != "succeeded":
        raise HTTPException(409, f"job {job_id!r} is {job.status}; results are there once it has succeeded")
    rel = (job.outputs or {}).get(name)
    if not rel:
        raise HTTPException(404, f"job {job_id!r} has no {name}")
    path = storage.resolve(rel)
    if not path.is_file():
        raise HTTPException(404, f"{name} of job {job_id!r} is missing from storage")
    return FileResponse(path, media_type=RESULT_FILES[name][1], filename=f"{job_id}-{name}")


_GLB: dict[int | str, dict[str, Any]] = {200: {"content": {"model/gltf-binary": {}}, "description": "Binary glTF"},
        404: {"model": ErrorOut}, 409: {"model": ErrorOut, "description": "The job has not succeeded"}}


@router.get("/{job_id}/result.glb", response_class=FileResponse, responses=_GLB,
            summary="The retargeted animation (after)")
def result_glb(job_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> FileResponse:
    return _result(job_id, "result.glb", session, key, storage)


@router.get("/{job_id}/before.glb", response_class=FileResponse, responses=_GLB,
            summary="The copy baseline (before)")
def before_glb(job_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> FileResponse:
    return _result(job_id, "before.glb", session, key, storage)


@router.get("/{job_id}/source.glb", response_class=FileResponse, responses=_GLB,
            summary="The source motion on its source body (when the pipeline wrote one)")
def source_glb(job_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> FileResponse:
    return _result(job_id, "source.glb", session, key, storage)


@router.get(
    "/{job_id}/metrics.json",
    response_class=FileResponse,
    summary="Metrics of before and after",
    responses={200: {"content": {"application/json": {}}, "description": "The metrics JSON"},
               404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
def metrics_json(job_id: str, session: SessionDep, key: CurrentKey, storage: StorageDep) -> FileResponse:
    return _result(job_id, "metrics.json", session, key, storage)
