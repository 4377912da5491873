"""A job whose pool process died is queued again at once, from the worker's main process.

When a pool process dies (killed, out of memory, crashed), Celery's main process learns of it at once: the task's
request fails with ``WorkerLostError``. Its message is also handed back to the broker (``task_reject_on_worker_lost``),
but that message names the attempt it was sent for, which may be older than the one that ran (a run that took
over a lost attempt runs the next one), so it cannot be trusted to restart the job. The row is the truth: the
attempt that process was running is settled here (queued again as the next attempt and sent, or ended), so the job
does not wait for the reaper's heartbeat timeout.
"""

from __future__ import annotations

import logging
from typing import Any

from billiard.exceptions import WorkerLostError
from celery import Celery
from celery.worker.request import Request

from api.db import session_scope, utcnow
from api.joblife import send_webhook, settle_lost
from api.models import Job
from api.outbox import submit
from api.settings import Settings, get_settings

log = logging.getLogger(__name__)


def requeue_dead_run(settings: Settings, celery: Celery, job_id: str, hostname: str, pid: int) -> str | None:
    """Settle the attempt of ``job_id`` that pool process ``pid`` of worker ``hostname`` was running; the outcome
    ('queued', 'canceled', 'failed'), or None when the row says that process was not running it."""
    url = settings.resolved_database_url
    with session_scope(url) as s:
        job = s.get(Job, job_id)
        if job is None or job.status != "running" or job.worker != hostname or job.worker_pid != pid:
            return None
        attempt, queue = job.attempt, job.queue
        mine = (Job.id == job_id, Job.attempt == attempt, Job.status == "running", Job.worker == hostname,
                Job.worker_pid == pid)
        outcome, delivery = settle_lost(s, job, mine, utcnow(), settings.max_job_attempts,
                                        settings.job_hard_time_limit_seconds, "its worker process was killed or crashed")
    if outcome == "queued":
        submit(url, celery, [(job_id, attempt + 1, queue)])
    send_webhook(celery, delivery)
    if outcome is not None:
        log.warning("job %s: pool process %s died running attempt %s; %s", job_id, pid, attempt,
                    f"queued again as attempt {attempt + 1}" if outcome == "queued" else outcome)
    return outcome


def is_worker_lost(exc: BaseException) -> bool:
    """True for the errors Celery reports when a pool process exits under a task."""
    exc = getattr(exc, "exc", exc)  # billiard wraps it in ExceptionWithTraceback
    return isinstance(exc, (WorkerLostError, SystemExit))


class JobRequest(Request):
    """The request of a job task in the main process: a lost pool process settles its job's row at once."""

    def on_failure(self, exc_info: Any, send_failed_event: bool = True, return_ok: bool = False) -> Any:
        job_id = (self.kwargs or {}).get("job_id")
        if job_id and self.worker_pid and is_worker_lost(exc_info.exception):
            try:
                requeue_dead_run(get_settings(), self.task.app, str(job_id), self.hostname, int(self.worker_pid))
            except Exception:  # the reaper still finds it after the heartbeat timeout
                log.exception("could not queue job %s again after its pool process died", job_id)
        return super().on_failure(exc_info, send_failed_event=send_failed_event, return_ok=return_ok)
