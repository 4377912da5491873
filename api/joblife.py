"""Job state changes shared by the API and the worker: send, cancel, retry, queue a webhook.

Every change is a conditional UPDATE on (id, attempt, status), so two processes acting on one job never both win.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from celery import Celery
from sqlalchemy import update
from sqlalchemy.orm import Session

from api.db import session_scope, updated, utcnow
from api.models import Job, WebhookDelivery
from api.queue import TASK_DELIVER_WEBHOOK, TASK_RUN_JOB

if TYPE_CHECKING:  # sentmarks sends with send_job
    from api.sentmarks import SentMarker

log = logging.getLogger(__name__)


def send_job(celery: Celery, job_id: str, attempt: int, queue: str) -> bool:
    """Put a run of a job on its queue; False (logged) when the broker cannot be reached (the reaper re-sends)."""
    try:
        celery.send_task(TASK_RUN_JOB, kwargs={"job_id": job_id, "attempt": attempt}, queue=queue)
        return True
    except Exception:
        log.exception("could not send job %s (attempt %s); the reaper will send it again", job_id, attempt)
        return False


def send_and_mark(url: str, celery: Celery, runs: list[tuple[str, int, str]], marker: SentMarker | None = None
                  ) -> None:
    """Send runs (job id, attempt, queue) to the broker, then record ``sent_at`` for those it took (now, or by
    ``marker`` in its next batch). A run whose send failed, or whose process died before recording it, is sent
    by the reaper within seconds."""
    sent = [(job_id, attempt) for job_id, attempt, queue in runs if send_job(celery, job_id, attempt, queue)]
    if not sent:
        return
    if marker is not None:
        marker.add(sent)
        return
    now = utcnow()
    with session_scope(url) as s:
        for job_id, attempt in sent:
            s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt, Job.sent_at.is_(None))
                      .values(sent_at=now))


def queue_webhook(session: Session, job: Job) -> str | None:
    """Record a delivery of the job's end event when it has a callback URL; returns the delivery id to send
    after the commit."""
    if not job.callback_url:
        return None
    delivery = WebhookDelivery(job_id=job.id, event=f"job.{job.status}", url=job.callback_url)
    session.add(delivery)
    session.flush()
    return delivery.id


def send_webhook(celery: Celery, delivery_id: str | None, attempt: int = 1, countdown: float | None = None) -> None:
    """Send attempt number ``attempt`` of a recorded delivery to the io queue (after its row is committed)."""
    if delivery_id is None:
        return
    try:
        celery.send_task(TASK_DELIVER_WEBHOOK, kwargs={"delivery_id": delivery_id, "attempt": attempt},
                         countdown=countdown)
    except Exception:
        log.exception("could not queue webhook delivery %s", delivery_id)


def cancel(session: Session, job: Job, reason: str = "canceled by the client") -> str:
    """Cancel a queued job at once, or ask a running one to stop. Returns 'canceled', 'requested' or 'finished'."""
    now = utcnow()
    if job.status == "queued":
        done = updated(session,
            update(Job).where(Job.id == job.id, Job.attempt == job.attempt, Job.status == "queued")
            .values(status="canceled", message=reason, finished_at=now, updated_at=now, cancel_requested=True)
        )
        if done:
            session.refresh(job)
            return "canceled"
        session.refresh(job)
    if job.status == "running":
        session.execute(
            update(Job).where(Job.id == job.id, Job.status == "running")
            .values(cancel_requested=True, updated_at=now)
        )
        session.refresh(job)
        return "requested" if job.status == "running" else "finished"
    return "finished"


def retry(session: Session, job: Job) -> bool:
    """Queue a failed or canceled job again as a new attempt; False when its state does not allow it."""
    now = utcnow()
    done = updated(session,
        update(Job)
        .where(Job.id == job.id, Job.attempt == job.attempt, Job.status.in_(("failed", "canceled")))
        .values(status="queued", attempt=job.attempt + 1, stage=None, progress=0.0, message=None, error_kind=None,
                cancel_requested=False, worker=None, worker_pid=None, started_at=None, heartbeat_at=None,
                finished_at=None, outputs=None, summary=None, stage_seconds=None, warnings=None, note=None,
                sent_at=None, updated_at=now)
    )
    session.refresh(job)
    return bool(done)
