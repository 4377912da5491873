"""The ``service`` fixture: real Redis, real worker processes and the API under uvicorn (see service_harness).

Redis is a private redis-server on a free port when the binary is there (the fault tests restart it), else a
spare database number of the shared one at 127.0.0.1:6379. The database is a throw-away PostgreSQL database when the server at RETARGET_TEST_PG_ADMIN (default
postgresql://postgres@127.0.0.1:5432/test) answers, as in docker-compose, and a SQLite file otherwise (the
embedded mode's test covers SQLite end to end). RETARGET_SERVICE_TEST_DB=sqlite|postgresql forces one.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from service_harness import REDIS_HOST, REDIS_PORT, REPO, PrivateRedis, Service, claim_clean_redis_db, free_port

from api.db import dispose_all
from api.migrate import upgrade

PG_ADMIN_URL = os.environ.get("RETARGET_TEST_PG_ADMIN", "postgresql://postgres@127.0.0.1:5432/test")


def choose_database(root: Path) -> tuple[str, Callable[[], None] | None]:
    """A database URL for the service, and how to drop it (None for SQLite)."""
    wanted = os.environ.get("RETARGET_SERVICE_TEST_DB", "auto")
    if wanted != "sqlite":
        try:
            import psycopg

            name = f"retarget_service_test_{secrets.token_hex(4)}"
            with psycopg.connect(PG_ADMIN_URL, autocommit=True, connect_timeout=2) as conn:
                conn.execute(f'CREATE DATABASE "{name}"')

            def drop() -> None:
                with psycopg.connect(PG_ADMIN_URL, autocommit=True) as conn:
                    conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

            return PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}", drop
        except Exception as exc:
            if wanted == "postgresql":
                pytest.fail(f"RETARGET_SERVICE_TEST_DB=postgresql but PostgreSQL is not usable: {exc}")
    return f"sqlite:///{root / 'service.sqlite'}", None


@pytest.fixture(scope="session")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    import redis

    root = tmp_path_factory.mktemp("service")
    private = PrivateRedis(root / "redis") if PrivateRedis.available() else None
    if private is not None:
        private.start()
        redis_url = private.url
        r = redis.Redis.from_url(redis_url)
    else:
        db, _ = claim_clean_redis_db()
        redis_url = f"redis://{REDIS_HOST}:{REDIS_PORT}/{db}"
        r = redis.Redis(REDIS_HOST, REDIS_PORT, db=db)
    data_dir, log_dir = root / "data", root / "logs"
    log_dir.mkdir()
    database_url, drop_database = choose_database(root)
    upgrade(database_url)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("RETARGET_API_") and k != "DATABASE_URL"}
    env.update({
        "PYTHONPATH": str(REPO),
        "RETARGET_API_DATA_DIR": str(data_dir),
        "RETARGET_API_DATABASE_URL": database_url,
        "REDIS_URL": redis_url,
        "RETARGET_API_MAX_UPLOAD_BYTES": str(32 * 1024 * 1024),
        "RETARGET_API_INSPECT_TIMEOUT_SECONDS": "90",
        "RETARGET_API_HEARTBEAT_INTERVAL_SECONDS": "0.5",
        "RETARGET_API_HEARTBEAT_TIMEOUT_SECONDS": "6",
        "RETARGET_API_REAPER_INTERVAL_SECONDS": "1",
        "RETARGET_API_PROGRESS_MIN_INTERVAL_SECONDS": "0.1",
        "RETARGET_API_WEBHOOK_BACKOFF_BASE_SECONDS": "0.5",
        "RETARGET_API_CALLBACK_ALLOWED_HOSTS": '["127.0.0.1"]',
        "OMP_NUM_THREADS": "1",
    })
    svc = Service(f"http://127.0.0.1:{port}", data_dir, database_url, env["REDIS_URL"], env, log_dir)
    svc.redis_server = private
    try:
        svc.start_worker("io", "io")
        svc.start_worker("cpu", "cpu")
        svc.start_worker("webhooks", "webhooks")
        svc.start("api", ["-m", "uvicorn", "api.main:create_app", "--factory", "--host", "127.0.0.1", "--port",
                          str(port), "--log-level", "warning"])
        svc.wait_ready()
        yield svc
    finally:
        svc.stop_all()
        dispose_all()
        if private is not None:
            private.stop()
        else:
            r.flushdb()
        if drop_database is not None:
            drop_database()
