"""Database engine and sessions: SQLite by default (WAL, busy timeout), PostgreSQL when configured.

Engines are cached per process id, so a forked worker child never reuses its parent's connections.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

from sqlalchemy import CursorResult, Engine, Executable, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

from api.settings import normalise_database_url

_LOCK = threading.Lock()
_ENGINES: dict[tuple[int, str], tuple[Engine, sessionmaker[Session]]] = {}


def utcnow() -> datetime:
    """Now, timezone-aware UTC."""
    return datetime.now(UTC)


def updated(session: Session, statement: Executable) -> int:
    """Execute an UPDATE or DELETE and return how many rows it changed."""
    return cast("CursorResult[Any]", session.execute(statement)).rowcount


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cur = dbapi_connection.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()


def make_engine(url: str) -> Engine:
    """A new engine for ``url`` with the connection settings this service needs."""
    url = normalise_database_url(url)
    if url.startswith("sqlite"):
        path = url.split("///", 1)[1] if "///" in url else ""
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=5, max_overflow=10)


def get_engine(url: str) -> Engine:
    """The engine of this process for ``url``."""
    return _get(url)[0]


def get_sessionmaker(url: str) -> sessionmaker[Session]:
    """The session factory of this process for ``url``."""
    return _get(url)[1]


def _get(url: str) -> tuple[Engine, sessionmaker[Session]]:
    url = normalise_database_url(url)
    key = (os.getpid(), url)
    found = _ENGINES.get(key)
    if found is not None:
        return found
    with _LOCK:
        found = _ENGINES.get(key)
        if found is None:
            engine = make_engine(url)
            found = (engine, sessionmaker(bind=engine, expire_on_commit=False))
            _ENGINES[key] = found
        return found


@contextmanager
def session_scope(url: str) -> Iterator[Session]:
    """A session that commits on success and rolls back on error."""
    session = get_sessionmaker(url)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def dispose_all() -> None:
    """Close every engine of this process (tests and shutdown)."""
    with _LOCK:
        for (pid, url), (engine, _) in list(_ENGINES.items()):
            if pid == os.getpid():
                engine.dispose()
                del _ENGINES[(pid, url)]
