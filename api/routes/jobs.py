"""``/v1/jobs``: submit, list, get, cancel, retry, and download results."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from api.deps import CeleryDep, CurrentKey, MarkerDep, SessionDep, SettingsDep, StorageDep
from api.idempotency import REPLAYED_HEADER, IdempotencyKey, fingerprint
from api.models import ApiKey, Job
from api.pages import MAX_QUERY_INT, page_bounds
from api.routing import SessionRoute
from api.schemas import ErrorOut, JobCreate, JobOut, JobStatus, Page
from api.serialize import job_out
from api.services import jobs as service
from api.services.submission import insert_job, prepare_job, read_job
from api.storage import Storage

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=SessionRoute)


def json_response(model: BaseModel, status_code: int = 200, headers: dict[str, str] | None = None) -> Response:
    """A response body already validated by its model (FastAPI would validate it again, in another thread)."""
    return Response(model.model_dump_json(), status_code=status_code, media_type="application/json",
                    headers=headers)


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
    values, replay = prepare_job(request.app.state.loop_reader, settings, key, body, idempotency_key, scope, fp)
    if values is None:
        assert replay is not None
        job, replayed = replay, True
    else:
        job, replayed = await insert_job(request.app.state, settings, celery, key, values, idempotency_key,
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
    deliveries = service.latest_deliveries(session, [j.id for j in rows])
    return Page[JobOut](
        items=[job_out(j, deliveries.get(j.id), note=service.note_for(j, settings)) for j in rows], total=total,
        limit=limit, offset=offset,
        next_offset=offset + limit if offset + limit < total else None,
    )



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
    return service.answer(session, service.cancel_job(session, celery, key, job_id), settings)


@router.post(
    "/{job_id}/retry",
    response_model=JobOut,
    status_code=202,
    summary="Run a failed or canceled job again",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
def retry_job(job_id: str, response: Response, session: SessionDep, key: CurrentKey, celery: CeleryDep,
              settings: SettingsDep, marker: MarkerDep, idempotency_key: IdempotencyKey = None) -> JobOut:
    job, replayed = service.retry_job(session, celery, key, job_id, idempotency_key, settings.resolved_database_url,
                                      marker)
    if replayed:
        response.headers[REPLAYED_HEADER] = "true"
    return service.answer(session, job, settings)


def _result(job_id: str, name: str, session: Session, key: ApiKey, storage: Storage) -> FileResponse:
    path = service.result_path(session, key, storage, job_id, name)
    return FileResponse(path, media_type=service.result_media_type(name), filename=f"{job_id}-{name}")


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
