"""The reaper: finds jobs whose worker vanished and sends them again, from the database rows.

Every worker process runs it periodically (worker/app.py), so it works the same with one embedded worker and
with many; each change is a conditional UPDATE, so two reapers never both re-send a job. What it does:

- a running job whose heartbeat is older than the timeout: canceled if a cancel was asked, failed if it ran
  past the hard time limit or used up its attempts, otherwise queued again as the next attempt and re-sent;
- a queued job whose message was not recorded as sent ``resend_unsent_after_seconds`` after its last change
  (broker down at submission, or the API died between commit and send), or was sent long ago: sent again
  (a duplicate message is harmless: a run only starts if the row is still queued at that attempt);
- a webhook delivery still pending long after its planned attempt: re-sent;
- old worker rows and worker-call rows: deleted.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import timedelta

from celery import Celery
from sqlalchemy import delete, or_, select, update

from api import idempotency
from api.db import session_scope, updated, utcnow
from api.joblife import send_webhook, settle_lost
from api.models import Job, WebhookDelivery, WorkerCall, WorkerProcess
from api.outbox import submit
from api.settings import Settings

log = logging.getLogger(__name__)

WEBHOOK_GRACE_SECONDS = 300.0
CLEANUP_AFTER = timedelta(days=1)


@dataclass
class ReapReport:
    requeued: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    canceled: list[str] = field(default_factory=list)
    resent: list[str] = field(default_factory=list)
    webhooks_resent: list[str] = field(default_factory=list)


def reap(settings: Settings, celery: Celery) -> ReapReport:
    """One pass of the reaper."""
    url = settings.resolved_database_url
    report = ReapReport()
    now = utcnow()
    stale = now - timedelta(seconds=settings.heartbeat_timeout_seconds)
    to_send: list[tuple[str, int, str]] = []
    deliveries: list[str | None] = []
    webhook_sends: list[tuple[str, int]] = []
    with session_scope(url) as s:
        dead = s.scalars(select(Job).where(Job.status == "running", Job.heartbeat_at < stale)).all()
        for job in dead:
            mine = (Job.id == job.id, Job.attempt == job.attempt, Job.status == "running", Job.heartbeat_at < stale)
            job_id, nxt, queue, worker, last = job.id, job.attempt + 1, job.queue, job.worker, job.heartbeat_at
            outcome, delivery = settle_lost(s, job, mine, now, settings.max_job_attempts,
                                            settings.job_hard_time_limit_seconds, "its worker stopped answering")
            if outcome == "queued":
                report.requeued.append(job_id)
                to_send.append((job_id, nxt, queue))
                log.warning("job %s: worker %s silent since %s; queued again as attempt %s", job_id, worker, last, nxt)
            elif outcome is not None:
                (report.canceled if outcome == "canceled" else report.failed).append(job_id)
                deliveries.append(delivery)

        resend_before = now - timedelta(seconds=settings.requeue_queued_after_seconds)
        never_before = now - timedelta(seconds=settings.resend_unsent_after_seconds)
        waiting = s.scalars(select(Job).where(
            Job.status == "queued",
            or_(Job.sent_at < resend_before, (Job.sent_at.is_(None)) & (Job.updated_at < never_before)),
        )).all()
        for job in waiting:
            job_id, attempt, queue = job.id, job.attempt, job.queue
            # claim the re-send (another reaper may be here too); sent_at is recorded again once it is sent
            n = updated(s, update(Job).where(Job.id == job_id, Job.attempt == attempt, Job.status == "queued",
                                             Job.sent_at == job.sent_at if job.sent_at else Job.sent_at.is_(None),
                                             Job.updated_at == job.updated_at)
                          .values(sent_at=None, updated_at=now))
            if n:
                report.resent.append(job_id)
                to_send.append((job_id, attempt, queue))

        late = now - timedelta(seconds=WEBHOOK_GRACE_SECONDS)
        stuck = s.scalars(select(WebhookDelivery).where(
            WebhookDelivery.status == "pending",
            or_(WebhookDelivery.next_attempt_at < late,
                WebhookDelivery.next_attempt_at.is_(None) & (WebhookDelivery.created_at < late)),
        )).all()
        for d in stuck:
            d.next_attempt_at = now
            report.webhooks_resent.append(d.id)
            webhook_sends.append((d.id, d.attempts + 1))

        old = now - CLEANUP_AFTER
        s.execute(delete(WorkerProcess).where(WorkerProcess.last_seen < old))
        s.execute(delete(WorkerCall).where(WorkerCall.created_at < old))
        idempotency.purge(s, settings.idempotency_ttl_seconds)

    submit(url, celery, to_send)
    for delivery_id in deliveries:
        send_webhook(celery, delivery_id)
    for d_id, attempt in webhook_sends:
        send_webhook(celery, d_id, attempt)
    return report
