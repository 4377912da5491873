"""Run the whole service as separate processes for the tests: a real Redis (a spare database number, flushed), real
Celery worker processes (``python -m worker``; not eager mode) and the API under uvicorn, on a temporary data
directory and SQLite database."""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from api.db import session_scope
from api.security import create_key

REPO = Path(__file__).resolve().parents[2]
REDIS_HOST, REDIS_PORT = "127.0.0.1", 6379
LOCK_KEY = "retarget-service-tests:lock"


def claim_redis_db() -> tuple[int, str]:
    """A Redis database number no one else uses now: empty, then claimed with a lock key."""
    import redis

    token = secrets.token_hex(8)
    for db in range(15, 0, -1):
        r = redis.Redis(REDIS_HOST, REDIS_PORT, db=db, socket_timeout=2)
        if r.dbsize() == 0 and r.set(LOCK_KEY, token, nx=True, ex=3600):
            return db, token
    raise RuntimeError("no empty Redis database (1-15) to run the service tests in")


def claim_clean_redis_db() -> tuple[int, str]:
    """Skip when Redis does not answer; otherwise a claimed, flushed database number and its lock token."""
    import pytest
    import redis

    try:
        redis.Redis(REDIS_HOST, REDIS_PORT, socket_timeout=2).ping()
    except Exception as exc:
        pytest.skip(f"Redis is not answering at {REDIS_HOST}:{REDIS_PORT}: {exc}")
    db, token = claim_redis_db()
    r = redis.Redis(REDIS_HOST, REDIS_PORT, db=db)
    r.flushdb()
    r.set(LOCK_KEY, token, ex=3600)
    return db, token


class PrivateRedis:
    """A redis-server of the tests' own (a free port, append-only file as docker-compose runs it), so a test may
    stop and start it without touching the machine's shared Redis."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None

    @staticmethod
    def available() -> bool:
        return shutil.which("redis-server") is not None

    @property
    def url(self) -> str:
        return f"redis://{REDIS_HOST}:{self.port}/0"

    def start(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        log = open(self.root / "redis.log", "ab")  # noqa: SIM115 (kept open with the process)
        self.proc = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", REDIS_HOST, "--dir", str(self.root), "--save", "",
             "--appendonly", "yes", "--appendfsync", "always"], stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True)
        import redis

        deadline = time.monotonic() + 20
        while True:
            try:
                redis.Redis(REDIS_HOST, self.port, socket_timeout=1).ping()
                return
            except redis.RedisError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    def stop(self) -> None:
        """SIGTERM: Redis flushes its append-only file and exits (a restart, not a data loss)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(20)
        self.proc = None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Service:
    """Handles of the running service."""

    base_url: str
    data_dir: Path
    database_url: str
    redis_url: str
    env: dict[str, str]
    log_dir: Path
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)
    redis_server: PrivateRedis | None = None

    def start(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        log = open(self.log_dir / f"{name}-{len(self.procs)}.log", "wb")  # noqa: SIM115 (kept open with the process)
        proc = subprocess.Popen([sys.executable, *args], cwd=REPO, env=self.env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[name] = proc
        return proc

    def start_worker(self, name: str, queues: str) -> subprocess.Popen[bytes]:
        return self.start(name, ["-m", "worker", "--queues", queues, "--concurrency", "1", "--loglevel", "INFO",
                                 "--name", f"{name}-{secrets.token_hex(3)}@%h"])

    def kill(self, name: str) -> None:
        """SIGKILL the whole process group (the worker and its pool children): a machine lost, not a shutdown."""
        proc = self.procs.pop(name)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)

    def stop_all(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 20
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()

    def log_tail(self, lines: int = 40) -> str:
        """The end of every process log (for assertion messages)."""
        out = []
        for path in sorted(self.log_dir.glob("*.log")):
            text = path.read_text(errors="replace").splitlines()[-lines:]
            out.append(f"--- {path.name}\n" + "\n".join(text))
        return "\n".join(out)

    def key(self, name: str) -> dict[str, str]:
        with session_scope(self.database_url) as s:
            _, plain = create_key(s, name)
        return {"X-API-Key": plain}

    def wait_ready(self, timeout: float = 180.0) -> dict[str, object]:
        deadline = time.monotonic() + timeout
        last: object = None
        while time.monotonic() < deadline:
            for name, proc in self.procs.items():
                if proc.poll() is not None:
                    raise RuntimeError(f"{name} exited with {proc.returncode}; see {self.log_dir}")
            try:
                r = httpx.get(f"{self.base_url}/readyz", timeout=5)
                last = r.json()
                if r.status_code == 200:
                    return r.json()  # type: ignore[no-any-return]
            except httpx.HTTPError as exc:
                last = exc
            time.sleep(0.5)
        raise TimeoutError(f"service not ready after {timeout} s: {last}")
