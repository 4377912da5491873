"""Record ``sent_at`` of jobs the broker took, a few at a time, off the request's path.

A submission used to write twice: the job row, then (after the broker send) its ``sent_at``. Under load the
second write doubles the database's write transactions (on SQLite each waits for the one write lock). The
API instead hands sent runs to this marker, whose thread writes every run sent in the last
``sent_mark_interval_seconds`` in one transaction. A run whose mark is lost (the process died first) looks
unsent, so the reaper sends it again; a duplicate message is harmless (a run only starts from ``queued``).
"""

from __future__ import annotations

import logging
import threading
import time

from sqlalchemy import bindparam, update

from api.db import get_engine, utcnow, write_lock
from api.models import Job

_JOBS = Job.__table__
_MARK = (update(Job).where(_JOBS.c.id == bindparam("run_id"), _JOBS.c.attempt == bindparam("run_attempt"),
                             _JOBS.c.sent_at.is_(None)).values(sent_at=bindparam("now")))

log = logging.getLogger(__name__)


class SentMarker:
    """A background thread that records ``sent_at`` for (job id, attempt) pairs in batches."""

    def __init__(self, url: str, interval_seconds: float) -> None:
        self.url = url
        self.interval = interval_seconds
        self._pending: list[tuple[str, int]] = []
        self._lock = threading.Lock()
        self._writing = threading.Lock()  # a flush waits for one in progress
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="sent-marker", daemon=True)
        self._thread.start()

    def add(self, runs: list[tuple[str, int]]) -> None:
        with self._lock:
            self._pending.extend(runs)
        self._wake.set()

    def flush(self) -> None:
        """Write what is pending now (in the caller's thread; after any write in progress)."""
        with self._writing:
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
            if not self._stopping:
                time.sleep(self.interval)  # gather what arrives meanwhile into the same write
            self.flush()

    def stop(self) -> None:
        self._stopping = True
        self._wake.set()
        self._thread.join(5)
        self.flush()
