"""Fixtures of the browser tests: the built front end, the real service (Redis, worker processes, uvicorn serving
frontend/dist at /), an API key, and Debian's Chromium driven by Python playwright (never `playwright install`).

The service is started with the process harness of the service tests (tests/service/service_harness.py).
Screenshots go to test-artifacts/e2e/ (gitignored).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
FRONTEND = REPO / "frontend"
ARTIFACTS = REPO / "test-artifacts" / "e2e"
CHROMIUM = Path(os.environ.get("RETARGET_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--enable-unsafe-swiftshader",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-dev-shm-usage",
]

sys.path.insert(0, str(REPO / "tests" / "service"))
from e2e_helpers import LAPTOP  # noqa: E402
from service_harness import (  # noqa: E402
    REDIS_HOST,
    REDIS_PORT,
    Service,
    claim_clean_redis_db,
    free_port,
)


def _newest_source_mtime() -> float:
    paths = [FRONTEND / "index.html", FRONTEND / "vite.config.js", FRONTEND / "package.json"]
    paths += [p for p in (FRONTEND / "src").rglob("*") if p.is_file()]
    return max(p.stat().st_mtime for p in paths if p.exists())


@pytest.fixture(scope="session")
def frontend_dist() -> Path:
    """frontend/dist, built with `npm run build` when missing or older than the sources."""
    dist = FRONTEND / "dist"
    index = dist / "index.html"
    if index.is_file() and index.stat().st_mtime >= _newest_source_mtime():
        return dist
    npm = shutil.which("npm")
    if npm is None or not (FRONTEND / "node_modules" / "vite").is_dir():
        if index.is_file():
            return dist  # stale but usable; say nothing more: the sources may be unchanged in content
        pytest.skip("frontend/dist is not built and npm or frontend/node_modules is missing (run `make setup`)")
    proc = subprocess.run([npm, "run", "build"], cwd=FRONTEND, capture_output=True, text=True, timeout=300)
    if proc.returncode != 0:
        pytest.fail(f"npm run build failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return dist


@pytest.fixture(scope="session")
def chromium() -> Path:
    if not CHROMIUM.is_file():
        pytest.skip(f"Chromium is not installed at {CHROMIUM} (Debian package `chromium`; set RETARGET_CHROMIUM)")
    return CHROMIUM


@pytest.fixture(scope="session")
def e2e_service(tmp_path_factory: pytest.TempPathFactory, frontend_dist: Path) -> Iterator[Service]:
    """API (serving the built front end), an io worker and a cpu worker, on a spare Redis database."""
    import redis

    from api.db import dispose_all
    from api.migrate import upgrade

    db, _ = claim_clean_redis_db()
    r = redis.Redis(REDIS_HOST, REDIS_PORT, db=db)
    root = tmp_path_factory.mktemp("e2e-service")
    data_dir, log_dir = root / "data", root / "logs"
    log_dir.mkdir()
    database_url = f"sqlite:///{root / 'service.sqlite'}"
    upgrade(database_url)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("RETARGET_API_") and k != "DATABASE_URL"}
    env.update({
        "PYTHONPATH": str(REPO),
        "RETARGET_API_DATA_DIR": str(data_dir),
        "RETARGET_API_DATABASE_URL": database_url,
        "REDIS_URL": f"redis://{REDIS_HOST}:{REDIS_PORT}/{db}",
        "RETARGET_API_FRONTEND_DIR": str(frontend_dist),
        "RETARGET_API_INSPECT_TIMEOUT_SECONDS": "90",
        "RETARGET_API_HEARTBEAT_INTERVAL_SECONDS": "1",
        "RETARGET_API_PROGRESS_MIN_INTERVAL_SECONDS": "0.1",
        "OMP_NUM_THREADS": "1",
    })  # fmt: skip
    svc = Service(f"http://127.0.0.1:{port}", data_dir, database_url, env["REDIS_URL"], env, log_dir)
    try:
        svc.start_worker("io", "io")
        svc.start_worker("cpu", "cpu")
        svc.start("api", ["-m", "uvicorn", "api.main:create_app", "--factory", "--host", "127.0.0.1", "--port",
                          str(port), "--log-level", "warning"])  # fmt: skip
        svc.wait_ready()
        yield svc
    finally:
        svc.stop_all()
        dispose_all()
        r.flushdb()


@pytest.fixture(scope="session")
def api_key(e2e_service: Service) -> str:
    return e2e_service.key("e2e")["X-API-Key"]


@pytest.fixture(scope="session")
def browser(chromium: Path) -> Iterator[Any]:
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS, timeout=60_000)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


class PageErrors(list[str]):
    """Uncaught page errors and console errors collected during a test."""


@pytest.fixture
def new_page(browser: Any) -> Iterator[Any]:
    """A factory of pages in fresh contexts (own localStorage); every page's errors are collected on it."""
    contexts = []

    def make(viewport: dict[str, int] = LAPTOP) -> Any:
        ctx = browser.new_context(viewport=viewport, accept_downloads=True)
        contexts.append(ctx)
        page = ctx.new_page()
        page.set_default_timeout(30_000)
        errors = PageErrors()
        page.on("pageerror", lambda e: errors.append(f"pageerror: {e}"))
        page.on("console", lambda m: errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
        page.errors = errors
        return page

    yield make
    for ctx in contexts:
        ctx.close()
