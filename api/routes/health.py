"""``/healthz`` (the process answers), ``/readyz`` (it can do work), ``/v1/info`` and ``/v1/me``."""

from __future__ import annotations

from datetime import timedelta
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import select, text

from api.db import utcnow
from api.deps import CeleryDep, CurrentKey, OptionalKey, SessionDep, SettingsDep, StorageDep
from api.models import WorkerProcess
from api.queue import IO_QUEUE, JOB_QUEUES, WEBHOOK_QUEUE
from api.routing import SessionRoute
from api.schemas import KeyInfo, ServiceInfo, StageOut
from api.security import SIGNATURE_HEADER
from api.serialize import RESULT_FILES
from api.services.assets import ALLOWED_FORMATS
from retarget_core.stages import STAGES

router = APIRouter(tags=["health"], route_class=SessionRoute)


def _version() -> str:
    try:
        return version("retarget")
    except PackageNotFoundError:
        return "0+unknown"


@router.get("/healthz", summary="Liveness: the API process answers")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get(
    "/readyz",
    summary="Readiness: database, broker, storage and a live worker",
    description="200 when every check passes, 503 otherwise; the body lists each check. A worker counts as live "
    "when its heartbeat is younger than RETARGET_API_HEARTBEAT_TIMEOUT_SECONDS. Worker host names are listed only "
    "for a request with a valid X-API-Key.",
    responses={503: {"description": "At least one check failed"}},
)
def readyz(session: SessionDep, settings: SettingsDep, storage: StorageDep, celery: CeleryDep,
           key: OptionalKey = None) -> JSONResponse:
    checks: dict[str, dict[str, Any]] = {}
    try:
        session.execute(text("SELECT 1"))
        checks["database"] = {"ok": True}
    except Exception as exc:
        checks["database"] = {"ok": False, "error": type(exc).__name__}
    try:
        with celery.connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, timeout=3)
            conn.default_channel  # opens a channel: proves the broker answers  # noqa: B018
        checks["broker"] = {"ok": True, "transport": "sqlite (embedded)" if settings.embedded_broker else "redis"}
    except Exception as exc:
        checks["broker"] = {"ok": False, "error": type(exc).__name__}
    try:
        storage.check_writable()
        checks["storage"] = {"ok": True}
    except Exception:
        checks["storage"] = {"ok": False, "error": "the data directory is not writable"}
    try:
        cutoff = utcnow() - timedelta(seconds=settings.heartbeat_timeout_seconds)
        live = session.scalars(select(WorkerProcess).where(WorkerProcess.last_seen >= cutoff)).all()
        queues = sorted({q for w in live for q in w.queues.split(",") if q})
        checks["workers"] = {
            "ok": bool(live) and any(q in queues for q in JOB_QUEUES) and IO_QUEUE in queues,
            "live_count": len(live),
            "queues": queues,
        }
        if key is not None:  # host names only for a key holder
            checks["workers"]["live"] = [{"hostname": w.hostname, "queues": w.queues.split(",")} for w in live]
        if WEBHOOK_QUEUE not in queues:
            checks["workers"]["warning"] = f"no live worker consumes the {WEBHOOK_QUEUE!r} queue: callbacks wait"
        if not checks["workers"]["ok"]:
            checks["workers"]["error"] = (
                "no live worker" if not live else f"no live worker consumes a job queue and the {IO_QUEUE!r} queue"
            )
    except Exception as exc:
        checks["workers"] = {"ok": False, "error": type(exc).__name__}
    ok = all(c["ok"] for c in checks.values())
    return JSONResponse({"status": "ready" if ok else "not ready", "checks": checks}, status_code=200 if ok else 503)


@router.get("/v1/info", response_model=ServiceInfo, summary="Limits and formats", tags=["info"])
def info(settings: SettingsDep) -> ServiceInfo:
    return ServiceInfo(
        version=_version(),
        max_upload_bytes=settings.max_upload_bytes,
        inspect_timeout_seconds=settings.inspect_timeout_seconds,
        max_batch_jobs=settings.max_batch_jobs,
        page_size_max=settings.page_size_max,
        queues=list(JOB_QUEUES),
        character_formats=list(ALLOWED_FORMATS["character"]),
        motion_formats=list(ALLOWED_FORMATS["motion"]),
        result_files=list(RESULT_FILES),
        stages=[StageOut(name=s.name, label=s.label, description=s.description, default=s.default,
                         available=s.available) for s in STAGES],
    )


@router.get("/v1/me", response_model=KeyInfo, summary="The calling API key", tags=["info"])
def me(key: CurrentKey, settings: SettingsDep) -> KeyInfo:
    return KeyInfo(id=key.id, name=key.name, key_prefix=key.key_prefix, created_at=key.created_at,
                   webhook_secret=settings.webhook_secret or key.webhook_secret, signature_header=SIGNATURE_HEADER)
