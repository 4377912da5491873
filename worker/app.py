"""The Celery worker: tasks by name, plus a maintenance thread (worker heartbeat row and the reaper).

Start it with ``python -m worker --queues cpu`` (jobs), ``python -m worker --queues io`` (uploads, bodies) and
``python -m worker --queues webhooks`` (callback deliveries, a thread pool), or with ``celery -A worker.app worker``.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Any

from celery import signals
from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy import delete

from api.db import session_scope, utcnow
from api.joblife import send_webhook
from api.models import WorkerProcess
from api.queue import (
    TASK_DELIVER_WEBHOOK,
    TASK_INSPECT,
    TASK_MAKE_BODY,
    TASK_REGISTER_BUILTINS,
    TASK_RUN_JOB,
    make_celery,
)
from api.settings import get_settings
from worker import assets, webhooks
from worker.reaper import reap
from worker.runner import JobRun

log = logging.getLogger("worker")

settings = get_settings()
os.environ.setdefault("RETARGET_PARSE_BUDGET_BYTES", str(settings.parse_budget_bytes))  # read by the readers
app = make_celery(settings, main="retarget-worker")


@app.task(name=TASK_RUN_JOB, bind=True, Request="worker.lost:JobRequest")
def run_job(self: Any, job_id: str, attempt: int) -> str:
    """Run one attempt of a job (a no-op when the row is not queued at that attempt: idempotent)."""
    hostname = self.request.hostname or f"worker@{os.uname().nodename}"
    result = JobRun(settings, job_id, attempt, hostname).run()
    send_webhook(app, result.webhook_delivery)
    log.info("job %s attempt %s: %s", job_id, attempt, result.outcome)
    return result.outcome


@app.task(name=TASK_INSPECT, time_limit=settings.inspect_time_limit_seconds,
          soft_time_limit=max(1, settings.inspect_time_limit_seconds - 5))
def inspect(call_id: str, ref: str, kind: str, label: str | None = None) -> None:
    """Parse a stored upload and answer the API's worker call."""
    try:
        assets.run_inspect(settings, call_id, ref, kind, label)
    except SoftTimeLimitExceeded:
        assets.answer(settings, call_id, error=f"{label or 'the file'}: reading it took longer than "
                      f"{settings.inspect_time_limit_seconds} s (setting RETARGET_API_INSPECT_TIME_LIMIT_SECONDS)")


@app.task(name=TASK_MAKE_BODY, time_limit=settings.inspect_time_limit_seconds,
          soft_time_limit=max(1, settings.inspect_time_limit_seconds - 5))
def make_body(call_id: str, params: dict[str, Any]) -> None:
    """Generate a body from shape parameters and answer the API's worker call."""
    try:
        assets.run_make_body(settings, call_id, params)
    except SoftTimeLimitExceeded:
        assets.answer(settings, call_id, error="making the body took too long")


@app.task(name=TASK_REGISTER_BUILTINS, time_limit=1800, soft_time_limit=1780)
def register_builtins() -> list[str]:
    """List and materialise the built-in bodies (sent by an io worker when it starts)."""
    try:
        return assets.register_builtins(settings)
    except ImportError as exc:
        log.warning("built-in bodies are not available in this worker: %s", exc)
        return []


@app.task(name=TASK_DELIVER_WEBHOOK, time_limit=int(4 * settings.webhook_timeout_seconds) + 10,
          soft_time_limit=int(3 * settings.webhook_timeout_seconds) + 5)
def deliver_webhook(delivery_id: str, attempt: int = 1) -> str:
    """One attempt of a webhook delivery; schedules the next attempt with backoff on failure."""
    outcome, delay = webhooks.deliver(settings, delivery_id, attempt)
    if outcome == "retry":
        send_webhook(app, delivery_id, attempt + 1, countdown=delay)
    return outcome


# Maintenance: the worker's own heartbeat row and the reaper, in a thread of the main worker process -----------
class ForkGuard:
    """Keeps the main process from forking a pool process while its maintenance thread is inside the database
    driver: a child forked then inherits the driver's locks taken (SQLite's global mutex) and hangs on its first
    query. A fork waits at most ``wait_seconds`` for the pass to end."""

    def __init__(self, wait_seconds: float = 10.0) -> None:
        self.lock = threading.Lock()
        self.wait_seconds = wait_seconds
        self._held = False

    def before_fork(self) -> None:
        self._held = self.lock.acquire(timeout=self.wait_seconds)

    def after_fork(self) -> None:
        if self._held:
            self._held = False
            self.lock.release()


FORK_GUARD = ForkGuard()
os.register_at_fork(before=FORK_GUARD.before_fork, after_in_parent=FORK_GUARD.after_fork,
                    after_in_child=FORK_GUARD.after_fork)


class Maintenance(threading.Thread):
    """Refreshes this worker's row (for /readyz) and runs the reaper periodically."""

    def __init__(self, hostname: str, queues: list[str]) -> None:
        super().__init__(name="retarget-maintenance", daemon=True)
        self.hostname = hostname
        self.queues = queues
        self.stop_event = threading.Event()
        self._last_reap = 0.0

    def beat(self) -> None:
        now = utcnow()
        with session_scope(settings.resolved_database_url) as s:
            row = s.get(WorkerProcess, self.hostname)
            if row is None:
                s.add(WorkerProcess(hostname=self.hostname, queues=",".join(self.queues), pid=os.getpid(),
                                    started_at=now, last_seen=now))
            else:
                row.queues, row.pid, row.last_seen = ",".join(self.queues), os.getpid(), now

    def run(self) -> None:
        import time

        while True:
            try:
                with FORK_GUARD.lock:
                    self.beat()
                    report = None
                    if time.monotonic() - self._last_reap >= settings.reaper_interval_seconds:
                        self._last_reap = time.monotonic()
                        report = reap(settings, app)
                if report is not None and any(vars(report).values()):
                    log.warning("reaper: %s", report)
            except Exception:
                log.exception("maintenance pass failed")
            if self.stop_event.wait(min(settings.heartbeat_interval_seconds, settings.reaper_interval_seconds)):
                return

    def remove(self) -> None:
        self.stop_event.set()
        try:
            with session_scope(settings.resolved_database_url) as s:
                s.execute(delete(WorkerProcess).where(WorkerProcess.hostname == self.hostname))
        except Exception:
            log.exception("could not remove worker row %s", self.hostname)


_maintenance: Maintenance | None = None


@signals.worker_ready.connect
def _on_ready(sender: Any = None, **_: Any) -> None:
    global _maintenance
    hostname = getattr(sender, "hostname", None) or f"worker@{os.uname().nodename}"
    try:
        queues = sorted(app.amqp.queues.consume_from.keys()) if app.amqp.queues.consume_from else []
    except Exception:
        queues = []
    _maintenance = Maintenance(hostname, queues)
    _maintenance.start()
    if "io" in queues:
        app.send_task(TASK_REGISTER_BUILTINS)
    log.info("worker %s ready on queues %s", hostname, queues)


@signals.worker_shutdown.connect
def _on_shutdown(**_: Any) -> None:
    if _maintenance is not None:
        _maintenance.remove()
