"""FastAPI dependencies as ``Annotated`` aliases: settings, database session, storage, Celery, the calling key."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from celery import Celery
from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import APIKeyHeader
from sqlalchemy.orm import Session

from api.db import get_sessionmaker
from api.models import ApiKey
from api.security import find_key
from api.settings import Settings
from api.storage import Storage

api_key_header = APIKeyHeader(
    name="X-API-Key", auto_error=False, description="Your API key (python -m api.keys create NAME)"
)


def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    session = get_sessionmaker(request.app.state.settings.resolved_database_url)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_celery(request: Request) -> Celery:
    return request.app.state.celery


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
SessionDep = Annotated[Session, Depends(get_session)]
StorageDep = Annotated[Storage, Depends(get_storage)]
CeleryDep = Annotated[Celery, Depends(get_celery)]


def current_key(session: SessionDep, key: Annotated[str | None, Security(api_key_header)] = None) -> ApiKey:
    """The key in the X-API-Key header; 401 when missing, unknown or revoked."""
    if not key:
        raise HTTPException(401, "missing API key: send it in the X-API-Key header",
                            headers={"WWW-Authenticate": "X-API-Key"})
    row = find_key(session, key)
    if row is None:
        raise HTTPException(401, "unknown or revoked API key", headers={"WWW-Authenticate": "X-API-Key"})
    session.commit()  # end the read: a long upload must not hold a database connection in a transaction
    return row


CurrentKey = Annotated[ApiKey, Depends(current_key)]
