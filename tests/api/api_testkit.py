"""Test helpers of the API tests: a recording Celery stand-in, a stand-in inspect worker, PostgreSQL databases."""

from __future__ import annotations

import os
import secrets
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from fastapi.testclient import TestClient
from kombu import Connection

from api.db import dispose_all, session_scope
from api.security import create_key
from api.settings import Settings

PG_ADMIN_URL = os.environ.get("RETARGET_TEST_PG_ADMIN", "postgresql://postgres@127.0.0.1:5432/test")


def pg_available() -> bool:
    try:
        import psycopg

        with psycopg.connect(PG_ADMIN_URL, connect_timeout=2):
            return True
    except Exception:
        return False


def make_pg_database(admin_url: str) -> tuple[str, Callable[[], None]]:
    """A new empty PostgreSQL database; returns its URL and a function that drops it."""
    import psycopg

    name = f"retarget_api_test_{secrets.token_hex(4)}"
    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    url = admin_url.rsplit("/", 1)[0] + f"/{name}"

    def drop() -> None:
        dispose_all()
        with psycopg.connect(admin_url, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    return url, drop


@dataclass
class Sent:
    name: str
    kwargs: dict[str, Any]
    queue: str | None
    countdown: float | None


@dataclass
class FakeCelery:
    """Records send_task calls; ``handlers[name](kwargs)`` stands in for a worker (run in a thread)."""

    sent: list[Sent] = field(default_factory=list)
    handlers: dict[str, Callable[[dict[str, Any]], None]] = field(default_factory=dict)
    fail: bool = False

    def send_task(self, name: str, args: Any = None, kwargs: dict[str, Any] | None = None, queue: str | None = None,
                  countdown: float | None = None, **_: Any) -> None:
        if self.fail:
            raise ConnectionError("broker down")
        self.sent.append(Sent(name, dict(kwargs or {}), queue, countdown))
        handler = self.handlers.get(name)
        if handler is not None:
            threading.Thread(target=handler, args=(dict(kwargs or {}),), daemon=True).start()

    def connection_for_write(self) -> Connection:
        return Connection("memory://")

    def named(self, name: str) -> list[Sent]:
        return [s for s in self.sent if s.name == name]


@dataclass
class ApiEnv:
    client: TestClient
    settings: Settings
    celery: FakeCelery
    url: str

    def key(self, name: str = "client") -> dict[str, str]:
        """Headers with a new API key."""
        with session_scope(self.url) as s:
            _, plain = create_key(s, name)
        return {"X-API-Key": plain}


def answer_inspect(settings: Settings, info: dict[str, Any] | None = None,
                   error_for: Callable[[dict[str, Any]], str | None] | None = None
                   ) -> Callable[[dict[str, Any]], None]:
    """A stand-in inspect worker: answers ok with ``info`` or the error ``error_for(kwargs)`` returns."""
    from worker.assets import answer

    def handler(kwargs: dict[str, Any]) -> None:
        err = error_for(kwargs) if error_for else None
        if err:
            answer(settings, kwargs["call_id"], error=err)
        else:
            answer(settings, kwargs["call_id"], {"info": dict(info or {"joints": ["Hips"], "kind": kwargs["kind"]})})

    return handler


