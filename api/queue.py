"""The Celery application as both sides configure it. The API only *sends* tasks, by name; it never imports worker/.

Queues: ``cpu`` and ``gpu`` carry retarget jobs (a worker consumes the queue of its device kind); ``io`` carries short
tasks the API waits for (parsing an upload, making a body), so they never wait behind a long job; ``webhooks``
carries callback deliveries, so a receiver that hangs never holds the processes uploads need.
"""

from __future__ import annotations

from celery import Celery
from kombu import Queue

from api import sqla_transport
from api.settings import Settings

TASK_RUN_JOB = "retarget.run_job"
TASK_INSPECT = "retarget.inspect"
TASK_MAKE_BODY = "retarget.make_body"
TASK_REGISTER_BUILTINS = "retarget.register_builtins"
TASK_DELIVER_WEBHOOK = "retarget.deliver_webhook"

JOB_QUEUES = ("cpu", "gpu")
IO_QUEUE = "io"
WEBHOOK_QUEUE = "webhooks"


def make_celery(settings: Settings, main: str = "retarget") -> Celery:
    """A Celery app for ``settings``: broker from REDIS_URL or the embedded SQLite transport; no result backend
    (results and progress are written to the database by the worker)."""
    sqla_transport.register()
    app = Celery(main, broker=settings.resolved_broker_url)
    transport_options: dict[str, object] = {}
    if settings.embedded_broker:
        transport_options["polling_interval"] = settings.broker_polling_interval_seconds
    else:
        # Redis re-delivers an unacknowledged message after this long; jobs may run up to the hard limit.
        transport_options["visibility_timeout"] = settings.job_hard_time_limit_seconds + 600
    app.conf.update(
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,
        result_backend=None,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        task_soft_time_limit=settings.job_soft_time_limit_seconds,
        task_time_limit=settings.job_hard_time_limit_seconds,
        task_queues=[Queue(name) for name in (*JOB_QUEUES, IO_QUEUE, WEBHOOK_QUEUE)],
        task_default_queue=IO_QUEUE,
        task_routes={
            TASK_INSPECT: {"queue": IO_QUEUE},
            TASK_MAKE_BODY: {"queue": IO_QUEUE},
            TASK_REGISTER_BUILTINS: {"queue": IO_QUEUE},
            TASK_DELIVER_WEBHOOK: {"queue": WEBHOOK_QUEUE},
        },
        broker_transport_options=transport_options,
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=5,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        worker_enable_remote_control=not settings.embedded_broker,
        enable_utc=True,
    )
    return app
