"""A short-lived per-process cache of API key lookups (hash of the presented key -> key row).

Polling clients present the same key many times a second; the cache saves a database round trip and a thread
per request. A revoked key stops working within ``key_cache_seconds``.
"""

from __future__ import annotations

import threading
import time

from sqlalchemy.orm import Session

from api.models import ApiKey
from api.security import find_key, hash_key


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

    def lookup(self, session: Session, key: str) -> ApiKey | None:
        """Find ``key`` in the database and remember it when it is active."""
        row = find_key(session, key)
        if row is not None and self.ttl > 0:
            session.expunge(row)
            with self._lock:
                if len(self._rows) >= self.size:
                    self._rows.clear()
                self._rows[hash_key(key)] = (time.monotonic() + self.ttl, row)
        return row

    def clear(self) -> None:
        with self._lock:
            self._rows.clear()
