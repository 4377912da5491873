"""FastAPI dependencies as ``Annotated`` aliases: settings, database session, storage, Celery, the calling key."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from celery import Celery
from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import APIKeyHeader
from sqlalchemy.orm import Session

from api.db import session_scope
from api.keycache import KeyCache
from api.models import ApiKey
from api.outbox import SentMarker
from api.settings import Settings
from api.storage import Storage

api_key_header = APIKeyHeader(
    name="X-API-Key", auto_error=False, description="Your API key (python -m api.keys create NAME)"
)


# These are ``async`` on purpose: FastAPI runs a plain ``def`` dependency in the thread pool, so each request
# would wait for a thread (behind the database work of every other request) just to read app.state.
async def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


async def get_session(request: Request) -> AsyncIterator[Session]:
    """A session for the request (:func:`api.db.session_scope`), ended on the event loop.

    The end (commit, or rollback on error) must not wait for a thread: under load every thread may be busy,
    and a request that holds a connection while it waits for a thread to give it back starves the pool (the
    threads wait for connections, the connections for threads). Ending a short transaction is quick."""
    with session_scope(request.app.state.settings.resolved_database_url) as session:
        yield session


async def get_storage(request: Request) -> Storage:
    return request.app.state.storage


async def get_celery(request: Request) -> Celery:
    return request.app.state.celery


async def get_marker(request: Request) -> SentMarker | None:
    """The process's outbox thread (None when runs are sent in the request: ``sent_mark_interval_seconds`` 0)."""
    return getattr(request.app.state, "sent_marker", None)


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
SessionDep = Annotated[Session, Depends(get_session)]
StorageDep = Annotated[Storage, Depends(get_storage)]
CeleryDep = Annotated[Celery, Depends(get_celery)]
MarkerDep = Annotated[SentMarker | None, Depends(get_marker)]


def _lookup(request: Request, key: str) -> ApiKey | None:
    cache: KeyCache = request.app.state.key_cache
    return cache.get(key) or cache.lookup(request.app.state.loop_reader, key)


async def current_key(request: Request, key: Annotated[str | None, Security(api_key_header)] = None) -> ApiKey:
    """The key in the X-API-Key header; 401 when missing, unknown or revoked. Found keys are cached for
    ``key_cache_seconds``; a lookup is one indexed read on the event loop (``KeyCache.lookup``)."""
    if not key:
        raise HTTPException(401, "missing API key: send it in the X-API-Key header",
                            headers={"WWW-Authenticate": "X-API-Key"})
    if len(key) > 200:
        raise HTTPException(401, "unknown or revoked API key", headers={"WWW-Authenticate": "X-API-Key"})
    row = _lookup(request, key)
    if row is None:
        raise HTTPException(401, "unknown or revoked API key", headers={"WWW-Authenticate": "X-API-Key"})
    return row


async def optional_key(request: Request, key: Annotated[str | None, Security(api_key_header)] = None) -> ApiKey | None:
    """The calling key when a valid one is sent, else None (for pages that show more to a key holder)."""
    if not key or len(key) > 200:
        return None
    return _lookup(request, key)


CurrentKey = Annotated[ApiKey, Depends(current_key)]
OptionalKey = Annotated[ApiKey | None, Depends(optional_key)]
