"""The FastAPI application: routers, CORS (off unless origins are set), and the front end at / when built."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from anyio import to_thread
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

from api import contract
from api.db import LoopReader, LoopWriter, configure_pool
from api.keycache import KeyCache
from api.outbox import SentMarker
from api.queue import make_celery
from api.routes import assets, batches, characters, health, jobs, reviews
from api.settings import Settings, get_settings
from api.storage import Storage

DESCRIPTION = """
Put a motion (BVH, glTF/GLB, FBX) onto a rigged character and get back an animated GLB, the plain-copy
"before" GLB and a metrics JSON.

Flow: upload a character and a motion (each answer says what the parser found), submit a job (202), poll it
or give a `callback_url`, download the results. Every request needs an API key in the `X-API-Key` header;
each key sees only its own resources (built-in bodies are shared).

Webhooks: when a job ends, its `callback_url` receives a POST with the job as JSON and the header
`X-Retarget-Signature: t=<unix time>,v1=<hex HMAC-SHA256 of "<t>.<body>">`, keyed with the secret from
`GET /v1/me`. Failed deliveries are retried with exponential backoff.
"""


class SPAStaticFiles(StaticFiles):
    """Static files that answer index.html for unknown paths without a file extension (client-side routes)."""

    async def get_response(self, path: str, scope: Scope):
        try:
            return await super().get_response(path, scope)
        except StarletteHTTPException as exc:
            if exc.status_code == 404 and "." not in path.rsplit("/", 1)[-1]:
                return await super().get_response("index.html", scope)
            raise


def create_app(settings: Settings | None = None) -> FastAPI:
    """A new application for ``settings`` (default: from the environment)."""
    settings = settings or get_settings()
    configure_pool(settings.db_pool_size, settings.db_max_overflow, settings.db_pool_timeout_seconds)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        to_thread.current_default_thread_limiter().total_tokens = settings.api_threads
        if settings.gil_switch_interval_seconds > 0:
            sys.setswitchinterval(settings.gil_switch_interval_seconds)
        marker = None
        if settings.sent_mark_interval_seconds > 0:
            marker = app.state.sent_marker = SentMarker(settings.resolved_database_url,
                                                         settings.sent_mark_interval_seconds)
        yield
        if marker is not None:
            marker.stop()
        app.state.loop_reader.close()
        app.state.loop_writer.close()

    app = FastAPI(
        lifespan=lifespan,
        title="Retarget service",
        version="1",
        description=DESCRIPTION,
        openapi_tags=[
            {"name": "characters", "description": "Target (and source) bodies: uploads, built-ins, generated"},
            {"name": "motions", "description": "Clips to retarget"},
            {"name": "jobs", "description": "One motion on one character, and its results"},
            {"name": "batches", "description": "Many motions on many characters"},
            {"name": "health", "description": "Liveness and readiness"},
            {"name": "info", "description": "Limits, formats, the calling key"},
        ],
    )
    storage = Storage(settings.data_dir)
    storage.ensure()
    app.state.settings = settings
    app.state.storage = storage
    app.state.key_cache = KeyCache(settings.key_cache_seconds)
    app.state.loop_reader = LoopReader(settings.resolved_database_url)
    app.state.loop_writer = LoopWriter(settings.resolved_database_url, settings.loop_write_wait_seconds)
    app.state.upload_slots = asyncio.Semaphore(settings.max_concurrent_uploads)
    app.state.celery = make_celery(settings, main="retarget-api")
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["*"],
            allow_headers=["*"],
            expose_headers=["Location", "Content-Disposition"],
        )
    for router in (health.router, assets.character_router, characters.router, assets.motion_router, jobs.router,
                   batches.router, reviews.router):
        app.include_router(router)
    contract.install(app)
    if (settings.frontend_dir / "index.html").is_file():
        app.mount("/", SPAStaticFiles(directory=settings.frontend_dir, html=True), name="frontend")
    return app
