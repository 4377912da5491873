"""Fixtures of the API tests: a fresh database (SQLite, and PostgreSQL when it answers), the app with a recording
Celery stand-in, and API keys. No worker process here (tests/service has those)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from api_testkit import PG_ADMIN_URL, ApiEnv, FakeCelery, answer_inspect, make_pg_database, pg_available
from fastapi.testclient import TestClient

from api.db import dispose_all
from api.main import create_app
from api.migrate import upgrade
from api.queue import TASK_INSPECT
from api.settings import Settings


@pytest.fixture(scope="session")
def pg_server() -> str:
    if not pg_available():
        pytest.skip(f"PostgreSQL is not reachable at {PG_ADMIN_URL}")
    return PG_ADMIN_URL


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A migrated empty database of each kind."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'db.sqlite'}"
        upgrade(url)
        yield url
        dispose_all()
        return
    admin = request.getfixturevalue("pg_server")
    url, drop = make_pg_database(admin)
    try:
        upgrade(url)
        yield url
    finally:
        drop()


@pytest.fixture
def api_env(tmp_path: Path, database_url: str) -> Iterator[ApiEnv]:
    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=database_url,
        inspect_timeout_seconds=5.0,
        max_upload_bytes=2 * 1024 * 1024,
        page_size_default=2,
        max_batch_jobs=6,
        frontend_dir=tmp_path / "no-frontend",
        callback_allowed_hosts=["127.0.0.1"],
    )
    app = create_app(settings)
    fake = FakeCelery()
    fake.handlers[TASK_INSPECT] = answer_inspect(settings)
    app.state.celery = fake
    with TestClient(app) as client:
        yield ApiEnv(client, settings, fake, settings.resolved_database_url)
