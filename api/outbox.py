"""The one way a job run reaches a worker: the committed job row is the outbox.

A run (job id, attempt, queue) is sent to the broker after its row is committed, then its ``sent_at`` is recorded.
A run whose send failed, or whose process died before recording it, looks unsent, so the reaper sends it (again)
within seconds; a duplicate message is harmless (a run only starts from ``queued`` at its attempt).

An API process hands its runs to a :class:`SentMarker`, whose thread sends them at once and records every run
sent in the last ``sent_mark_interval_seconds`` in one transaction (under load, one write for many submissions;
on SQLite each write waits for the one write lock). Worker processes and an API without a marker send and record
in the caller's thread (:func:`submit` without a marker).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from sqlalchemy import bindparam, update

from api.db import get_engine, utcnow, write_lock
from api.models import Job
from api.queue import TASK_RUN_JOB

Run = tuple[str, int, str]
"""A job run to send: job id, attempt, queue."""

_JOBS = Job.__table__
MARK_SENT = (update(Job).where(_JOBS.c.id == bindparam("run_id"), _JOBS.c.attempt == bindparam("run_attempt"),
                               _JOBS.c.sent_at.is_(None)).values(sent_at=bindparam("now")))
"""Record that a run's message was sent (only while its row is still unmarked at that attempt)."""

log = logging.getLogger(__name__)


def send_job(celery: Any, job_id: str, attempt: int, queue: str) -> bool:
    """Put a run of a job on its queue; False (logged) when the broker cannot be reached (the reaper re-sends)."""
    try:
        celery.send_task(TASK_RUN_JOB, kwargs={"job_id": job_id, "attempt": attempt}, queue=queue)
        return True
    except Exception:
        log.exception("could not send job %s (attempt %s); the reaper will send it again", job_id, attempt)
        return False


def send_runs(celery: Any, runs: list[Run]) -> list[tuple[str, int]]:
    """Send runs; the (job id, attempt) of those the broker took."""
    return [(job_id, attempt) for job_id, attempt, queue in runs if send_job(celery, job_id, attempt, queue)]


def mark_sent(url: str, sent: list[tuple[str, int]]) -> None:
    """Record ``sent_at`` of sent runs in one transaction; logged, not raised, on failure (the reaper re-sends)."""
    if not sent:
        return
    now = utcnow()
    try:
        with write_lock(url), get_engine(url).begin() as conn:  # one executemany
            conn.execute(MARK_SENT, [{"run_id": job_id, "run_attempt": attempt, "now": now} for job_id, attempt in sent])
    except Exception:
        log.exception("could not record sent_at of %d jobs", len(sent))


def submit(url: str, celery: Any, runs: list[Run], marker: SentMarker | None = None) -> None:
    """Send committed runs and record them: from ``marker``'s thread when there is one, else now."""
    if not runs:
        return
    if marker is not None:
        marker.send(celery, runs)
    else:
        mark_sent(url, send_runs(celery, runs))


class SentMarker:
    """A background thread that sends committed runs at once and records their ``sent_at`` in batches."""

    def __init__(self, url: str, interval_seconds: float) -> None:
        self.url = url
        self.interval = interval_seconds
        self._pending: list[tuple[str, int]] = []
        self._unsent: list[tuple[Any, Run]] = []  # (celery app, run)
        self._lock = threading.Lock()
        self._writing = threading.Lock()  # a flush waits for one in progress
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="sent-marker", daemon=True)
        self._thread.start()

    def send(self, celery: Any, runs: list[Run]) -> None:
        """Send committed runs from the thread at once, then record them."""
        with self._lock:
            self._unsent.extend((celery, run) for run in runs)
        self._wake.set()

    def _send_unsent(self) -> None:
        with self._lock:
            todo, self._unsent = self._unsent, []
        sent = [pair for celery, run in todo for pair in send_runs(celery, [run])]
        if sent:
            with self._lock:
                self._pending.extend(sent)

    def flush(self) -> None:
        """Send and record what is pending now (in the caller's thread; after any flush in progress)."""
        with self._writing:
            self._send_unsent()
            with self._lock:
                sent, self._pending = self._pending, []
            mark_sent(self.url, sent)

    def _run(self) -> None:
        while not self._stopping:
            self._wake.wait()
            self._wake.clear()
            with self._writing:
                self._send_unsent()  # at once: a job's start waits for its message
            if not self._stopping:
                time.sleep(self.interval)  # gather what arrives meanwhile into the same write
            self.flush()

    def stop(self) -> None:
        self._stopping = True
        self._wake.set()
        self._thread.join(5)
        self.flush()
