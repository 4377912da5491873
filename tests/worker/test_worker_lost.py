"""The worker's main process settles the job of a pool process that died (worker/lost.py), and never forks a pool
process while its maintenance thread is inside the database driver (worker/app.py ForkGuard)."""

from __future__ import annotations

import os
import threading
import time

from worker_testkit import Recorder, add_job

from api.db import session_scope, utcnow
from api.models import Job, WebhookDelivery
from api.queue import TASK_DELIVER_WEBHOOK, TASK_RUN_JOB
from api.settings import Settings
from worker.lost import is_worker_lost, requeue_dead_run

HOST = "cpu-1@test"


def running(settings: Settings, pid: int, attempt: int = 1, **values: object) -> str:
    """A job that pool process ``pid`` of worker HOST is running at ``attempt``."""
    job_id = add_job(settings, **values)
    with session_scope(settings.resolved_database_url) as s:
        job = s.get(Job, job_id)
        assert job is not None
        job.status, job.attempt, job.worker, job.worker_pid = "running", attempt, HOST, pid
        job.started_at = job.heartbeat_at = utcnow()
    return job_id


def row(settings: Settings, job_id: str) -> Job:
    with session_scope(settings.resolved_database_url) as s:
        job = s.get(Job, job_id)
        assert job is not None
        return job


def test_the_dead_process_job_is_queued_again_and_sent(wsettings: Settings) -> None:
    job_id = running(wsettings, pid=4242)
    celery = Recorder()
    assert requeue_dead_run(wsettings, celery, job_id, HOST, 4242) == "queued"  # type: ignore[arg-type]
    job = row(wsettings, job_id)
    assert (job.status, job.attempt, job.worker_pid) == ("queued", 2, None) and job.sent_at is not None
    assert "attempt 1 stopped (its worker process was killed or crashed)" in (job.note or "")
    assert celery.sent == [(TASK_RUN_JOB, {"job_id": job_id, "attempt": 2}, "cpu", None)]


def test_another_process_or_worker_or_state_is_left_alone(wsettings: Settings) -> None:
    job_id = running(wsettings, pid=4242)
    celery = Recorder()
    assert requeue_dead_run(wsettings, celery, job_id, HOST, 999) is None  # type: ignore[arg-type]
    assert requeue_dead_run(wsettings, celery, job_id, "cpu-2@test", 4242) is None  # type: ignore[arg-type]
    assert row(wsettings, job_id).status == "running" and celery.sent == []


def test_last_attempt_fails_with_its_webhook(wsettings: Settings) -> None:
    job_id = running(wsettings, pid=77, attempt=wsettings.max_job_attempts, callback_url="http://127.0.0.1:9/h")
    celery = Recorder()
    assert requeue_dead_run(wsettings, celery, job_id, HOST, 77) == "failed"  # type: ignore[arg-type]
    job = row(wsettings, job_id)
    assert job.status == "failed" and job.error_kind == "worker_lost" and job.finished_at is not None
    with session_scope(wsettings.resolved_database_url) as s:
        assert s.query(WebhookDelivery).filter_by(job_id=job_id, event="job.failed").count() == 1
    assert [name for name, *_ in celery.sent] == [TASK_DELIVER_WEBHOOK]


def test_worker_lost_errors_are_recognised() -> None:
    from billiard.einfo import ExceptionWithTraceback
    from billiard.exceptions import WorkerLostError

    lost = WorkerLostError("Worker exited prematurely: signal 9 (SIGKILL)")
    assert is_worker_lost(lost) and is_worker_lost(ExceptionWithTraceback(lost, "tb")) and is_worker_lost(SystemExit(1))
    assert not is_worker_lost(ValueError("boom"))


def test_a_fork_waits_for_the_maintenance_pass() -> None:
    from worker.app import FORK_GUARD

    entered = threading.Event()

    def maintenance_pass() -> None:
        with FORK_GUARD.lock:
            entered.set()
            time.sleep(0.5)

    thread = threading.Thread(target=maintenance_pass)
    thread.start()
    entered.wait(5)
    start = time.monotonic()
    pid = os.fork()
    if pid == 0:  # the child: the guard is free here too
        os._exit(0 if FORK_GUARD.lock.acquire(timeout=1) else 1)
    waited = time.monotonic() - start
    _, status = os.waitpid(pid, 0)
    thread.join()
    assert waited >= 0.3 and os.WEXITSTATUS(status) == 0, (waited, status)
    assert FORK_GUARD.lock.acquire(timeout=1)
    FORK_GUARD.lock.release()
