"""The reaper on database rows: dead workers' jobs are queued again, limits end them, nothing is sent twice."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import update
from worker_testkit import Recorder, add_job

from api.db import session_scope, utcnow
from api.models import Job, WebhookDelivery, WorkerCall, WorkerProcess
from api.queue import TASK_DELIVER_WEBHOOK, TASK_RUN_JOB
from api.settings import Settings
from worker.reaper import reap


def set_running(settings: Settings, job_id: str, silent_for: float, ran_for: float = 10.0, **values: object) -> None:
    now = utcnow()
    with session_scope(settings.resolved_database_url) as s:
        s.execute(update(Job).where(Job.id == job_id).values(
            status="running", worker="dead@host", started_at=now - timedelta(seconds=ran_for),
            heartbeat_at=now - timedelta(seconds=silent_for), **values))


def row(settings: Settings, job_id: str) -> Job:
    with session_scope(settings.resolved_database_url) as s:
        r = s.get(Job, job_id)
        assert r is not None
        return r


def test_silent_running_job_is_queued_again_once(wsettings: Settings) -> None:
    dead, alive = add_job(wsettings), add_job(wsettings)
    set_running(wsettings, dead, silent_for=5.0)
    set_running(wsettings, alive, silent_for=0.1)
    rec = Recorder()
    report = reap(wsettings, rec)  # type: ignore[arg-type]
    assert report.requeued == [dead]
    assert rec.sent == [(TASK_RUN_JOB, {"job_id": dead, "attempt": 2}, "cpu", None)]
    r = row(wsettings, dead)
    assert r.status == "queued" and r.attempt == 2 and r.worker is None and r.heartbeat_at is None
    assert row(wsettings, alive).status == "running"
    # a second reaper (another worker) finds nothing to do
    rec2 = Recorder()
    assert reap(wsettings, rec2).requeued == [] and rec2.sent == []  # type: ignore[arg-type]


def test_limits_end_a_job_instead_of_requeueing(wsettings: Settings) -> None:
    spent = add_job(wsettings, callback_url="http://127.0.0.1:9/h")
    set_running(wsettings, spent, silent_for=5.0, attempt=wsettings.max_job_attempts)
    slow = add_job(wsettings)
    set_running(wsettings, slow, silent_for=5.0, ran_for=wsettings.job_hard_time_limit_seconds + 1)
    canceled = add_job(wsettings)
    set_running(wsettings, canceled, silent_for=5.0, cancel_requested=True)
    rec = Recorder()
    report = reap(wsettings, rec)  # type: ignore[arg-type]
    assert sorted(report.failed) == sorted([spent, slow]) and report.canceled == [canceled]
    assert row(wsettings, spent).error_kind == "worker_lost" and "stopped 3 times" in row(wsettings, spent).message
    assert row(wsettings, slow).error_kind == "timeout" and "hard limit" in row(wsettings, slow).message
    assert row(wsettings, canceled).status == "canceled"
    assert [s[0] for s in rec.sent] == [TASK_DELIVER_WEBHOOK]  # only the job with a callback_url
    assert not any(s[0] == TASK_RUN_JOB for s in rec.sent)


def test_queued_jobs_never_sent_or_sent_long_ago_are_sent_again(wsettings: Settings) -> None:
    old = utcnow() - timedelta(seconds=wsettings.requeue_queued_after_seconds + 5)
    a_minute_ago = utcnow() - timedelta(seconds=60)
    never = add_job(wsettings, sent_at=None, created_at=a_minute_ago, updated_at=a_minute_ago)
    fresh_never = add_job(wsettings, sent_at=None)
    long_ago = add_job(wsettings, sent_at=old)
    recent = add_job(wsettings, sent_at=utcnow())
    rec = Recorder()
    report = reap(wsettings, rec)  # type: ignore[arg-type]
    assert sorted(report.resent) == sorted([never, long_ago])
    assert {s[1]["job_id"] for s in rec.sent} == {never, long_ago}
    assert row(wsettings, never).sent_at is not None and row(wsettings, fresh_never).sent_at is None
    assert row(wsettings, recent).status == "queued"


def test_stuck_webhooks_and_old_rows(wsettings: Settings) -> None:
    job_id = add_job(wsettings)
    long_ago = utcnow() - timedelta(days=2)
    with session_scope(wsettings.resolved_database_url) as s:
        s.add(WebhookDelivery(id="whd_1", job_id=job_id, event="job.succeeded", url="http://x", attempts=2,
                              next_attempt_at=utcnow() - timedelta(hours=1)))
        s.add(WebhookDelivery(id="whd_2", job_id=job_id, event="job.succeeded", url="http://x", attempts=1,
                              next_attempt_at=utcnow() + timedelta(seconds=30)))
        s.add(WorkerProcess(hostname="gone@h", queues="cpu", pid=1, last_seen=long_ago))
        s.add(WorkerProcess(hostname="here@h", queues="cpu", pid=2))
        s.add(WorkerCall(op="x", created_at=long_ago))
    rec = Recorder()
    report = reap(wsettings, rec)  # type: ignore[arg-type]
    assert report.webhooks_resent == ["whd_1"]
    assert rec.sent == [(TASK_DELIVER_WEBHOOK, {"delivery_id": "whd_1", "attempt": 3}, None, None)]
    with session_scope(wsettings.resolved_database_url) as s:
        assert s.get(WorkerProcess, "gone@h") is None and s.get(WorkerProcess, "here@h") is not None
        assert s.query(WorkerCall).count() == 0
