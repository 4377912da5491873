"""A short-lived per-process cache of API key lookups (hash of the presented key -> key row).

Polling clients present the same key many times a second; the cache saves a database round trip per request.
A revoked key stops working within ``key_cache_seconds``. A lookup is one read by the key's unique hash, made on
the event loop through the process's :class:`~api.db.LoopReader` (no thread hand-off), so the many requests
that find a key expired at the same moment each cost one indexed read, not a wait for a thread.
"""

from __future__ import annotations

import threading
import time

from sqlalchemy import bindparam, select
from sqlalchemy.orm import make_transient_to_detached

from api.db import LoopReader
from api.models import ApiKey
from api.security import hash_key

_KEYS = ApiKey.__table__
_KEY_BY_HASH = select(_KEYS).where(_KEYS.c.key_hash == bindparam("key_hash"))


class KeyCache:
    """Remembers found keys (not unknown ones) for ``ttl`` seconds; at most ``size`` entries."""

    def __init__(self, ttl: float, size: int = 10_000) -> None:
        self.ttl = ttl
        self.size = size
        self._rows: dict[str, tuple[float, ApiKey]] = {}
        self._lock = threading.Lock()

    def get(self, key: str) -> ApiKey | None:
        """The cached row of ``key`` when it is fresh."""
        if self.ttl <= 0:
            return None
        found = self._rows.get(hash_key(key))
        if found is None or found[0] < time.monotonic():
            return None
        return found[1]

    def lookup(self, reader: LoopReader, key: str) -> ApiKey | None:
        """Find the active row of ``key`` in the database (a detached ApiKey) and remember it."""
        digest = hash_key(key)
        rows = reader.rows(_KEY_BY_HASH, {"key_hash": digest})
        if not rows or rows[0].revoked_at is not None:
            return None
        row = ApiKey(**rows[0]._asdict())
        make_transient_to_detached(row)  # as if loaded and expunged: never inserted again by a session
        if self.ttl > 0:
            with self._lock:
                if len(self._rows) >= self.size:
                    self._rows.clear()
                self._rows[digest] = (time.monotonic() + self.ttl, row)
        return row

    def clear(self) -> None:
        with self._lock:
            self._rows.clear()
