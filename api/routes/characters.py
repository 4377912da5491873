"""``/v1/characters``: uploaded characters, built-in bodies, and bodies made from shape parameters."""

from __future__ import annotations

from fastapi import HTTPException, Response
from starlette.concurrency import run_in_threadpool

from api.deps import CeleryDep, CurrentKey, SettingsDep
from api.models import new_id
from api.queue import TASK_MAKE_BODY
from api.routes.assets import _insert_asset, make_router
from api.schemas import AssetOut, BodyCreate, ErrorOut
from api.worker_calls import WorkerCallFailed, WorkerUnavailable, call_worker

router = make_router("character")


@router.post(
    "/builtin",
    status_code=201,
    response_model=AssetOut,
    summary="Make a body from shape parameters",
    description="A worker generates a MakeHuman body (22-joint skin) from the parameters and stores it as a "
    "character of yours (origin `generated`). Built-in presets are listed by GET /v1/characters with "
    "`builtin: true` and can be used directly by id (`builtin:<preset>`).",
    responses={422: {"model": ErrorOut, "description": "Invalid parameters"},
               503: {"model": ErrorOut, "description": "No worker answered in time"}},
)
async def make_body(body: BodyCreate, response: Response, key: CurrentKey, settings: SettingsDep,
                    celery: CeleryDep) -> AssetOut:
    url = settings.resolved_database_url
    try:
        result = await call_worker(celery, url, TASK_MAKE_BODY, {"params": body.params},
                                   settings.inspect_timeout_seconds)
    except WorkerCallFailed as exc:
        raise HTTPException(422, str(exc)) from exc
    except WorkerUnavailable as exc:
        raise HTTPException(503, str(exc)) from exc
    name = body.name or result.get("name") or "generated body"
    out = await run_in_threadpool(
        _insert_asset, url,
        id=new_id("chr"), kind="character", owner_id=key.id, origin="generated", name=name[:300],
        filename=f"{name[:200]}.glb", format="glb", sha256=result["sha256"], size_bytes=result["size_bytes"],
        info=result["info"], params=result.get("params", body.params),
    )
    response.headers["Location"] = out.links["self"]
    return out
