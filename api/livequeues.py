"""Which queues live workers consume, as this API process last saw it (cached for a moment: status polls read it).

A queued job on a queue no live worker serves gets a note saying so, instead of waiting silently.
"""

from __future__ import annotations

import threading
import time
from datetime import timedelta

from sqlalchemy import select

from api.db import LoopReader, session_scope, utcnow
from api.models import WorkerProcess
from api.settings import Settings

_LOCK = threading.Lock()
_CACHE: dict[str, tuple[float, frozenset[str]]] = {}


def live_queues(settings: Settings, reader: LoopReader | None = None) -> frozenset[str]:
    """Queues consumed by a worker whose heartbeat is younger than ``heartbeat_timeout_seconds`` (read through
    ``reader`` when given: on the event loop)."""
    url = settings.resolved_database_url
    now = time.monotonic()
    found = _CACHE.get(url)
    if found is not None and found[0] > now:
        return found[1]
    cutoff = utcnow() - timedelta(seconds=settings.heartbeat_timeout_seconds)
    statement = select(WorkerProcess.queues).where(WorkerProcess.last_seen >= cutoff)
    if reader is not None:
        rows = [row[0] for row in reader.rows(statement)]
    else:
        with session_scope(url) as s:
            rows = list(s.scalars(statement).all())
    queues = frozenset(q for row in rows for q in row.split(",") if q)
    with _LOCK:
        _CACHE[url] = (now + settings.worker_queue_cache_seconds, queues)
    return queues


def waiting_note(queue: str, settings: Settings, reader: LoopReader | None = None) -> str | None:
    """A note for a queued job when no live worker serves its queue, else None."""
    if queue in live_queues(settings, reader):
        return None
    return (f"no worker serves the {queue!r} queue now: the job waits until one starts (start one with "
            f"`python -m worker --queues {queue}`, or submit with another queue)")
