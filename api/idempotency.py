"""``Idempotency-Key`` on every POST that creates work: the same key again answers with what the first request
made, instead of making it twice.

The record is written in the same transaction as the resource, so a request either made both or neither. A
second request with the key finds the record and answers with the resource as it is now (header
``Idempotent-Replayed: true``); the same key with a different request is refused (422). Two requests racing
with one key: the database's unique constraint lets one win, the other then answers like a repeat.
"""

from __future__ import annotations

import hashlib
from datetime import timedelta
from typing import Annotated

from fastapi import Header, HTTPException
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from api.db import utcnow
from api.models import IdempotencyRecord

HEADER = "Idempotency-Key"
REPLAYED_HEADER = "Idempotent-Replayed"

IdempotencyKey = Annotated[
    str | None,
    Header(alias=HEADER, max_length=200, description="Any unique string (a UUID): a repeated request with the same "
           "key answers with what the first one made, and makes nothing new"),
]


def fingerprint(*parts: str | bytes) -> str:
    """The SHA-256 of what a request asked for."""
    digest = hashlib.sha256()
    for part in parts:
        digest.update(part.encode() if isinstance(part, str) else part)
        digest.update(b"\x00")
    return digest.hexdigest()


def find(session: Session, owner_id: str, key: str | None, scope: str, fp: str) -> str | None:
    """The resource id an earlier request with ``key`` made, or None; 422 when that request was a different one."""
    if not key:
        return None
    row = session.scalar(select(IdempotencyRecord).where(IdempotencyRecord.owner_id == owner_id,
                                                         IdempotencyRecord.key == key))
    if row is None:
        return None
    if row.scope != scope or row.fingerprint != fp:
        raise HTTPException(422, f"the Idempotency-Key {key[:80]!r} was already used for a different request "
                                 f"({row.scope}); use a new key for a new request")
    return row.resource_id


def remember(session: Session, owner_id: str, key: str | None, scope: str, fp: str, resource_id: str) -> None:
    """Record that ``key`` made ``resource_id`` (in the caller's transaction)."""
    if key:
        session.add(IdempotencyRecord(owner_id=owner_id, key=key, scope=scope, fingerprint=fp,
                                      resource_id=resource_id))


def purge(session: Session, ttl_seconds: float) -> int:
    """Forget keys older than ``ttl_seconds``; returns how many."""
    cutoff = utcnow() - timedelta(seconds=ttl_seconds)
    result = session.execute(delete(IdempotencyRecord).where(IdempotencyRecord.created_at < cutoff))
    return int(getattr(result, "rowcount", 0) or 0)
