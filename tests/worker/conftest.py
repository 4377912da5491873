"""Fixtures of the worker tests: settings on a migrated database (SQLite, and PostgreSQL when it answers),
a recording Celery stand-in, and job rows with stored inputs. The worker code runs in this process."""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from pathlib import Path

import pytest

from api.db import dispose_all
from api.migrate import upgrade
from api.settings import Settings
from api.storage import Storage

PG_ADMIN_URL = os.environ.get("RETARGET_TEST_PG_ADMIN", "postgresql://postgres@127.0.0.1:5432/test")


@pytest.fixture(params=["sqlite", "postgresql"])
def wsettings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    """Settings with a fresh data directory and database; short heartbeats."""
    drop = None
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'w.sqlite'}"
    else:
        try:
            import psycopg

            name = f"retarget_worker_test_{secrets.token_hex(4)}"
            with psycopg.connect(PG_ADMIN_URL, autocommit=True, connect_timeout=2) as conn:
                conn.execute(f'CREATE DATABASE "{name}"')
        except Exception as exc:
            pytest.skip(f"PostgreSQL is not reachable at {PG_ADMIN_URL}: {exc}")
        url = PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"

        def drop() -> None:
            with psycopg.connect(PG_ADMIN_URL, autocommit=True) as conn:
                conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    upgrade(url)
    settings = Settings(data_dir=tmp_path / "data", database_url=url, heartbeat_interval_seconds=0.2,
                        heartbeat_timeout_seconds=2.0, progress_min_interval_seconds=0.0,
                        callback_allowed_hosts=["127.0.0.1"])
    Storage(settings.data_dir).ensure()
    yield settings
    dispose_all()
    if drop:
        drop()


@pytest.fixture
def sqlite_settings(tmp_path: Path) -> Iterator[Settings]:
    """Like wsettings, SQLite only (for tests that are about files rather than the database)."""
    url = f"sqlite:///{tmp_path / 'w.sqlite'}"
    upgrade(url)
    settings = Settings(data_dir=tmp_path / "data", database_url=url, heartbeat_interval_seconds=0.2,
                        heartbeat_timeout_seconds=2.0, progress_min_interval_seconds=0.0,
                        callback_allowed_hosts=["127.0.0.1"])
    Storage(settings.data_dir).ensure()
    yield settings
    dispose_all()
