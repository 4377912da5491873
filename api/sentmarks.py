"""Send submitted jobs to the broker and record their ``sent_at``, a few at a time, off the request's path.

A submission used to write twice: the job row, then (after the broker send) its ``sent_at``. Under load the
second write doubles the database's write transactions (on SQLite each waits for the one write lock). The
API instead hands runs to this marker, whose thread writes every run sent in the last
``sent_mark_interval_seconds`` in one transaction. A submission also hands it the send itself
(:meth:`SentMarker.send`): the job row is committed before the answer, so it is the outbox: the thread sends
at once, and a run whose send failed, or whose process died first, looks unsent, so the reaper sends it
(again) within seconds; a duplicate message is harmless (a run only starts from ``queued``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from sqlalchemy import bindparam, update

from api.db import get_engine, utcnow, write_lock
from api.joblife import send_job
from api.models import Job

_JOBS = Job.__table__
_MARK = (update(Job).where(_JOBS.c.id == bindparam("run_id"), _JOBS.c.attempt == bindparam("run_attempt"),
                             _JOBS.c.sent_at.is_(None)).values(sent_at=bindparam("now")))

log = logging.getLogger(__name__)


class SentMarker:
    """A background thread that sends runs (job id, attempt, queue) and records ``sent_at`` for (job id, attempt)
    pairs in batches."""

    def __init__(self, url: str, interval_seconds: float) -> None:
        self.url = url
        self.interval = interval_seconds
        self._pending: list[tuple[str, int]] = []
        self._unsent: list[tuple[Any, str, int, str]] = []  # (celery app, job id, attempt, queue)
        self._lock = threading.Lock()
        self._writing = threading.Lock()  # a flush waits for one in progress
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="sent-marker", daemon=True)
        self._thread.start()

    def add(self, runs: list[tuple[str, int]]) -> None:
        """Record ``sent_at`` of runs already sent (in the next batch)."""
        with self._lock:
            self._pending.extend(runs)
        self._wake.set()

    def send(self, celery: Any, runs: list[tuple[str, int, str]]) -> None:
        """Send committed runs (job id, attempt, queue) from the thread at once, then record them."""
        with self._lock:
            self._unsent.extend((celery, *run) for run in runs)
        self._wake.set()

    def _send_unsent(self) -> None:
        with self._lock:
            runs, self._unsent = self._unsent, []
        sent = [(job_id, attempt) for celery, job_id, attempt, queue in runs
                if send_job(celery, job_id, attempt, queue)]
        if sent:
            with self._lock:
                self._pending.extend(sent)

    def flush(self) -> None:
        """Send and write what is pending now (in the caller's thread; after any flush in progress)."""
        with self._writing:
            self._send_unsent()
            with self._lock:
                runs, self._pending = self._pending, []
            if not runs:
                return
            now = utcnow()
            try:
                with write_lock(self.url), get_engine(self.url).begin() as conn:  # one executemany
                    conn.execute(_MARK, [{"run_id": job_id, "run_attempt": attempt, "now": now}
                                         for job_id, attempt in runs])
            except Exception:  # the reaper re-sends what stays unmarked
                log.exception("could not record sent_at of %d jobs", len(runs))

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
