"""``/v1/characters/builtin``: bodies made from shape parameters (uploads, lists and downloads of characters are
the asset routes)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response
from starlette.concurrency import run_in_threadpool

from api import idempotency
from api.deps import CeleryDep, CurrentKey, SettingsDep
from api.models import new_id
from api.queue import TASK_MAKE_BODY
from api.routing import SessionRoute
from api.schemas import AssetOut, BodyCreate, ErrorOut
from api.services.assets import answer_asset, insert_asset, replayed_asset
from api.uploads import safe_filename
from api.worker_calls import WorkerCallFailed, WorkerUnavailable, call_worker

router = APIRouter(prefix="/v1/characters", tags=["characters"], route_class=SessionRoute)


@router.post(
    "/builtin",
    status_code=201,
    response_model=AssetOut,
    summary="Make a body from shape parameters",
    description="A worker generates a MakeHuman body (22-joint skin) from the parameters and stores it as a "
    "character of yours (origin `generated`). Built-in presets are listed by GET /v1/characters with "
    "`builtin: true` and can be used directly by id (`builtin:<preset>`). With an Idempotency-Key header, a "
    "repeated request answers with the body the first one made.",
    responses={422: {"model": ErrorOut, "description": "Invalid parameters"},
               503: {"model": ErrorOut, "description": "No worker answered in time"}},
)
async def make_body(body: BodyCreate, response: Response, key: CurrentKey, settings: SettingsDep,
                    celery: CeleryDep, idempotency_key: idempotency.IdempotencyKey = None) -> AssetOut:
    url = settings.resolved_database_url
    scope, fp = "POST /v1/characters/builtin", idempotency.fingerprint(body.model_dump_json())
    earlier = await run_in_threadpool(replayed_asset, url, key.id, idempotency_key, scope, fp)
    if earlier is not None:
        return answer_asset(response, earlier, True)
    params = body.params.model_dump(exclude_unset=True)
    try:
        result = await call_worker(celery, url, TASK_MAKE_BODY, {"params": params},
                                   settings.inspect_timeout_seconds)
    except WorkerCallFailed as exc:
        raise HTTPException(422, str(exc)) from exc
    except WorkerUnavailable as exc:
        raise HTTPException(503, str(exc)) from exc
    name = body.name or result.get("name") or "generated body"
    out, replayed = await run_in_threadpool(
        insert_asset, url, (idempotency_key, scope, fp) if idempotency_key else None,
        id=new_id("chr"), kind="character", owner_id=key.id, origin="generated", name=name[:300],
        filename=safe_filename(f"{name[:200]}.glb") or "body.glb", format="glb", sha256=result["sha256"], size_bytes=result["size_bytes"],
        info=result["info"], params=result.get("params", params),
    )
    return answer_asset(response, out, replayed)
