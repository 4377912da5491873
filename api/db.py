"""Database engine and sessions: SQLite by default (WAL, busy timeout), PostgreSQL when configured.

Engines are cached per process id, so a forked worker child never reuses its parent's connections. Pool sizes
come from :func:`configure_pool` (the API calls it with its settings; pool size + overflow must cover the API's
thread count, so no thread ever waits for a connection that another waiting request holds).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext, suppress
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

from sqlalchemy import CursorResult, Engine, Executable, Row, create_engine, event
from sqlalchemy.engine import Connection
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import StaticPool

from api.settings import normalise_database_url

_LOCK = threading.Lock()
_ENGINES: dict[tuple[int, str], tuple[Engine, sessionmaker[Session]]] = {}


@dataclass(frozen=True)
class PoolConfig:
    """Connection pool of each engine (per process)."""

    size: int = 10
    max_overflow: int = 30
    timeout_seconds: float = 10.0


_POOL = PoolConfig()


def configure_pool(size: int, max_overflow: int, timeout_seconds: float) -> None:
    """Set the pool of engines made from now on in this process (call before the first query)."""
    global _POOL
    _POOL = PoolConfig(size, max_overflow, timeout_seconds)


_WRITE_LOCKS: dict[str, threading.Lock] = {}


def write_lock(url: str) -> AbstractContextManager[Any]:
    """For SQLite, a lock the writing threads of this process take in turn around a commit; a no-op elsewhere.

    SQLite has one write lock per file, and a thread that finds it taken sleeps in SQLite's busy handler in
    growing steps (up to 100 ms each), so under many concurrent writers the unlucky ones wait seconds. Taking
    turns in the process leaves SQLite's handler only the other processes to wait for."""
    if not normalise_database_url(url).startswith("sqlite"):
        return nullcontext()
    lock = _WRITE_LOCKS.get(url)
    if lock is None:
        with _LOCK:
            lock = _WRITE_LOCKS.setdefault(url, threading.Lock())
    return lock


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
        pool: dict[str, Any] = {}
        if path and path != ":memory:":
            pool = {"pool_size": _POOL.size, "max_overflow": _POOL.max_overflow, "pool_timeout": _POOL.timeout_seconds}
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False}, **pool)
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=_POOL.size, max_overflow=_POOL.max_overflow,
                         pool_timeout=_POOL.timeout_seconds)


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


class LoopReader:
    """One connection of its own for short reads made on the event loop itself (status polls).

    Handing a read that takes a fraction of a millisecond to a thread costs more than the read (the hand-off,
    the thread's wake-up, the GIL passed back and forth), and a thread may wait behind others' work. The event
    loop of an API process instead reads through this connection, which no thread shares, so it never waits
    for the pool. Only single-row reads by key belong here: they never wait for a lock (SQLite in WAL mode and
    PostgreSQL let readers pass writers). PostgreSQL reads are in autocommit (one round trip, no BEGIN or
    COMMIT); a connection found broken is replaced and the read tried once more."""

    def __init__(self, url: str) -> None:
        self.url = normalise_database_url(url)
        self._engine: Engine | None = None
        self._conn: Connection | None = None
        self._pid = os.getpid()

    def _connection(self) -> Connection:
        if self._conn is None or self._pid != os.getpid():
            if self._engine is None or self._pid != os.getpid():
                self._pid = os.getpid()
                if self.url.startswith("sqlite"):
                    self._engine = create_engine(self.url, poolclass=StaticPool,
                                                 connect_args={"timeout": 30, "check_same_thread": False})
                    event.listen(self._engine, "connect", _sqlite_pragmas)
                else:
                    self._engine = create_engine(self.url, poolclass=StaticPool, isolation_level="AUTOCOMMIT")
            self._conn = self._engine.connect()
        return self._conn

    def rows(self, statement: Executable, params: dict[str, Any] | None = None) -> list[Row[Any]]:
        """The rows of a SELECT, its transaction ended (SQLite keeps no snapshot open between reads)."""
        for retry in (False, True):
            conn = self._connection()
            try:
                result = list(conn.execute(statement, params).all())
                conn.rollback()
                return result
            except DBAPIError as exc:
                self.close()
                if retry or not exc.connection_invalidated:
                    raise
            except BaseException:
                self.close()
                raise
        raise AssertionError("unreachable")

    def close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            with suppress(Exception):  # a broken connection may refuse to close cleanly
                conn.close()
        if self._engine is not None and self._pid == os.getpid():
            self._engine.dispose()
        self._engine = None


class LoopWriter:
    """A connection of its own for the one short write of a submission, made on the event loop.

    A thread hand-off costs a busy loop more than the write: the answer waits for the thread, the interpreter
    lock and two more turns of the loop behind every poll that arrived meanwhile. The write must not wait long
    for others, though, since the whole process waits with it: SQLite waits at most ``wait_seconds`` for the
    write lock (its busy timeout), PostgreSQL at most that long for a row lock (``lock_timeout``). A write that
    fails with :class:`~sqlalchemy.exc.OperationalError` (busy, lock timeout, broken connection; nothing was
    written) is for the caller to make again in a thread. Each write checks out a fresh ``Connection`` (one
    database connection underneath), so a change of isolation level never outlives the write."""

    def __init__(self, url: str, wait_seconds: float = 0.02) -> None:
        self.url = normalise_database_url(url)
        self.wait_ms = max(1, int(wait_seconds * 1000))
        self._engine: Engine | None = None
        self._pid = os.getpid()

    def connect(self) -> Connection:
        """A connection to write through (use it as a context manager)."""
        if self._engine is None or self._pid != os.getpid():
            self._pid = os.getpid()
            if self.url.startswith("sqlite"):
                self._engine = create_engine(self.url, poolclass=StaticPool,
                                             connect_args={"timeout": self.wait_ms / 1000, "check_same_thread": False})
                event.listen(self._engine, "connect", _sqlite_pragmas)
                event.listen(self._engine, "connect", self._sqlite_busy_timeout)  # after the pragmas' 30 s
            else:
                self._engine = create_engine(self.url, poolclass=StaticPool,
                                             connect_args={"options": f"-c lock_timeout={self.wait_ms}"})
        return self._engine.connect()

    def _sqlite_busy_timeout(self, dbapi_connection: Any, _record: Any) -> None:
        cur = dbapi_connection.cursor()
        cur.execute(f"PRAGMA busy_timeout={self.wait_ms}")
        cur.close()

    def close(self) -> None:
        """Close the connection (the next write opens a new one)."""
        if self._engine is not None and self._pid == os.getpid():
            self._engine.dispose()
        self._engine = None


def dispose_all() -> None:
    """Close every engine of this process (tests and shutdown)."""
    with _LOCK:
        for (pid, url), (engine, _) in list(_ENGINES.items()):
            if pid == os.getpid():
                engine.dispose()
                del _ENGINES[(pid, url)]
