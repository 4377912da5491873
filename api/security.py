"""API keys (stored as SHA-256) and webhook signatures (HMAC-SHA256)."""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time

from sqlalchemy import select
from sqlalchemy.orm import Session

from api.models import ApiKey

KEY_PREFIX = "rk_"
SIGNATURE_HEADER = "X-Retarget-Signature"
"""``t=<unix seconds>,v1=<hex HMAC-SHA256 of "<t>.<raw body>" with the secret>``"""


def hash_key(key: str) -> str:
    """The stored form of an API key."""
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def generate_key() -> str:
    """A new random API key (shown once; only its hash is stored)."""
    return KEY_PREFIX + secrets.token_urlsafe(32)


def create_key(session: Session, name: str, key: str | None = None) -> tuple[ApiKey, str]:
    """Store a new key (``key`` given: that value, e.g. a development key). Returns the row and the plain key."""
    plain = key or generate_key()
    row = ApiKey(name=name, key_hash=hash_key(plain), key_prefix=plain[:8])
    session.add(row)
    session.flush()
    return row, plain


def ensure_key(session: Session, name: str, key: str) -> ApiKey:
    """The row of ``key``, created when missing (the embedded mode's development key)."""
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    if row is None:
        row, _ = create_key(session, name, key)
    return row


def find_key(session: Session, key: str) -> ApiKey | None:
    """The active key row for a presented key, or None."""
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    if row is None or row.revoked_at is not None:
        return None
    return row


def sign_payload(secret: str, body: bytes, timestamp: int | None = None) -> str:
    """The value of the signature header for ``body`` sent at ``timestamp``."""
    ts = int(time.time()) if timestamp is None else int(timestamp)
    mac = hmac.new(secret.encode("utf-8"), f"{ts}.".encode() + body, hashlib.sha256).hexdigest()
    return f"t={ts},v1={mac}"


def verify_signature(secret: str, body: bytes, header: str, tolerance_seconds: float | None = 300) -> bool:
    """True when ``header`` is a valid signature of ``body`` (and, with a tolerance, recent). For receivers."""
    try:
        parts = dict(item.split("=", 1) for item in header.split(","))
        ts = int(parts["t"])
        given = parts["v1"]
    except (KeyError, ValueError):
        return False
    if tolerance_seconds is not None and abs(time.time() - ts) > tolerance_seconds:
        return False
    expected = sign_payload(secret, body, ts).split("v1=", 1)[1]
    return hmac.compare_digest(expected, given)
