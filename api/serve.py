"""``python -m api.serve``: the whole service on one machine, no Docker, no Redis.

Upgrades the database, makes sure a development API key exists (printed), starts three workers (``cpu`` jobs,
``io`` short tasks, ``webhooks`` deliveries; restarted if they die) and serves the API (and the front end when built) with
uvicorn. Broker: Celery's SQLAlchemy transport on a SQLite file under the data directory, or Redis when REDIS_URL
is set; database: SQLite under the data directory, or DATABASE_URL.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
import time

import uvicorn

from api.db import session_scope
from api.main import create_app
from api.migrate import upgrade
from api.security import ensure_key
from api.settings import Settings, get_settings

DEFAULT_DEV_KEY = "retarget-dev-key"
log = logging.getLogger("api.serve")


class WorkerSupervisor(threading.Thread):
    """Starts worker subprocesses and starts them again when they exit unexpectedly."""

    def __init__(self, commands: list[list[str]]) -> None:
        super().__init__(name="worker-supervisor", daemon=True)
        self.commands = commands
        self.procs: list[subprocess.Popen[bytes] | None] = [None] * len(commands)
        self.stopping = threading.Event()

    def _start(self, i: int) -> None:
        self.procs[i] = subprocess.Popen(self.commands[i])

    def run(self) -> None:
        for i in range(len(self.commands)):
            self._start(i)
        while not self.stopping.wait(2.0):
            for i, p in enumerate(self.procs):
                if p is None or p.poll() is None or self.stopping.is_set():
                    continue
                if p.returncode in (0, -signal.SIGINT, -signal.SIGTERM):  # asked to stop (Ctrl-C reaches it too)
                    self.procs[i] = None
                    continue
                log.warning("worker %s exited with %s; starting it again", self.commands[i], p.returncode)
                time.sleep(1.0)
                self._start(i)

    def stop(self, timeout: float = 20.0) -> None:
        self.stopping.set()
        for p in self.procs:
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for p in self.procs:
            if p is None:
                continue
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def worker_commands(settings: Settings, concurrency: int) -> list[list[str]]:
    """The job worker (cpu queue), the short-task worker (io queue) and the callback worker (webhooks queue)."""
    py = sys.executable
    return [
        [py, "-m", "worker", "--queues", "cpu", "--concurrency", str(concurrency)],
        [py, "-m", "worker", "--queues", "io", "--concurrency", "2"],
        [py, "-m", "worker", "--queues", "webhooks", "--concurrency", "8"],
    ]


def main(argv: list[str] | None = None) -> None:
    settings = get_settings()
    parser = argparse.ArgumentParser(prog="python -m api.serve", description=__doc__.splitlines()[0])
    parser.add_argument("--host", default=settings.host)
    parser.add_argument("--port", type=int, default=settings.port)
    parser.add_argument("--concurrency", type=int, default=settings.worker_concurrency,
                        help="job processes of the cpu worker")
    parser.add_argument("--no-worker", action="store_true", help="serve the API only (workers run elsewhere)")
    parser.add_argument("--no-dev-key", action="store_true", help="do not create the development API key")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    settings.data_dir.mkdir(parents=True, exist_ok=True)
    upgrade(settings.resolved_database_url)
    if not args.no_dev_key:
        key = settings.dev_api_key or DEFAULT_DEV_KEY
        with session_scope(settings.resolved_database_url) as s:
            ensure_key(s, "development key", key)
    broker = "Redis" if not settings.embedded_broker else "SQLite (embedded, no server)"
    print(f"retarget service on http://{args.host}:{args.port}  (docs: /docs)", flush=True)
    print(f"  data: {settings.data_dir.resolve()}  broker: {broker}", flush=True)
    if not args.no_dev_key:
        print(f"  development API key: {key}   (header X-API-Key; set RETARGET_API_DEV_API_KEY to change it)",
              flush=True)

    supervisor = None
    if not args.no_worker:
        os.environ["RETARGET_API_DATA_DIR"] = str(settings.data_dir.resolve())
        supervisor = WorkerSupervisor(worker_commands(settings, args.concurrency))
        supervisor.start()
    # uvicorn re-raises SIGTERM after its own shutdown; with Python's default action the process would die there
    # and leave the workers running. A handler that exits normally lets ``finally`` stop them.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="info")
    finally:
        if supervisor is not None:
            supervisor.stop()


if __name__ == "__main__":
    main()
