"""Job state changes shared by the API and the worker: cancel, retry, settle a lost run, queue a webhook
(sending runs is :mod:`api.outbox`).

Every change is a conditional UPDATE on (id, attempt, status), so two processes acting on one job never both win.
"""

from __future__ import annotations

import logging
from datetime import datetime

from celery import Celery
from sqlalchemy import ColumnElement, update
from sqlalchemy.orm import Session

from api.db import updated, utcnow
from api.models import Job, WebhookDelivery
from api.queue import TASK_DELIVER_WEBHOOK

log = logging.getLogger(__name__)


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


def settle_lost(session: Session, job: Job, where: tuple[ColumnElement[bool], ...], now: datetime, max_attempts: int,
                hard_limit_seconds: float, cause: str, sent: bool = False) -> tuple[str | None, str | None]:
    """End or repeat a running attempt whose process is gone (``where``: the conditions that it still is).

    Canceled when a cancel was asked, failed past the hard time limit or after ``max_attempts`` runs, otherwise
    queued again as the next attempt (``sent``: its message is on its way already). Returns the outcome
    ('queued', 'canceled', 'failed', or None when another process changed the row first) and the webhook
    delivery to send after the commit."""
    lost, nxt = job.attempt, job.attempt + 1
    ran = (now - job.started_at).total_seconds() if job.started_at else 0.0
    if job.cancel_requested:
        values = {"status": "canceled", "message": "canceled by the client (its worker had stopped)"}
    elif ran >= hard_limit_seconds:
        values = {"status": "failed", "error_kind": "timeout",
                  "message": f"the job ran longer than the hard limit of {hard_limit_seconds:g} s (setting "
                  "RETARGET_API_JOB_HARD_TIME_LIMIT_SECONDS); try a shorter frame range"}
    elif lost >= max_attempts:
        values = {"status": "failed", "error_kind": "worker_lost",
                  "message": f"the worker running this job stopped {lost} times (crash, out of memory, killed or "
                  "shut down); it was not started again"}
    else:
        n = updated(session, update(Job).where(*where).values(
            status="queued", attempt=nxt, stage=None, progress=0.0, worker=None, worker_pid=None, started_at=None,
            heartbeat_at=None, sent_at=now if sent else None, updated_at=now,
            note=f"attempt {lost} stopped ({cause}); running again as attempt {nxt}"))
        return ("queued" if n else None), None
    if not updated(session, update(Job).where(*where).values(finished_at=now, updated_at=now, **values)):
        return None, None
    session.refresh(job)
    return str(values["status"]), queue_webhook(session, job)
