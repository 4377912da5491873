"""Review links: a signed, expiring token that opens one job's review (its state and result files) read-only.

Token: ``<link id>.<expiry unix seconds>.<hex HMAC-SHA256 of "<link id>.<job id>.<expiry>">``. The signature
proves the server made it for that job and expiry; the database row lets its owner revoke it. The secret is the
setting ``review_link_secret`` or a random key kept in ``<data_dir>/secrets/review-link.key`` (shared by every API
process on the data directory).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import secrets
from datetime import datetime
from pathlib import Path

from api.models import ReviewLink
from api.settings import Settings


def secret(settings: Settings) -> bytes:
    """The signing key of review links."""
    if settings.review_link_secret:
        return settings.review_link_secret.encode()
    path = Path(settings.data_dir) / "secrets" / "review-link.key"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        tmp = path.with_suffix(f".{secrets.token_hex(4)}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(secrets.token_hex(32))
        with contextlib.suppress(FileExistsError):
            os.link(tmp, path)  # the first process to get here wins; the others read its key
        tmp.unlink(missing_ok=True)
    return path.read_text().strip().encode()


def _mac(key: bytes, link_id: str, job_id: str, expiry: int) -> str:
    return hmac.new(key, f"{link_id}.{job_id}.{expiry}".encode(), hashlib.sha256).hexdigest()


def make_token(settings: Settings, link: ReviewLink) -> str:
    """The token of a link row."""
    expiry = int(link.expires_at.timestamp())
    return f"{link.id}.{expiry}.{_mac(secret(settings), link.id, link.job_id, expiry)}"


def parse_token(token: str) -> tuple[str, int, str] | None:
    """(link id, expiry, signature) of a well-formed token, else None."""
    parts = token.split(".")
    if len(parts) != 3 or not parts[1].isdigit() or len(parts[1]) > 12 or len(parts[2]) != 64:
        return None
    return parts[0], int(parts[1]), parts[2]


def valid(settings: Settings, link: ReviewLink | None, token: str, now: datetime) -> bool:
    """True when ``token`` is the signed, unexpired, unrevoked token of ``link``."""
    parsed = parse_token(token)
    if link is None or parsed is None or link.revoked_at is not None:
        return False
    link_id, expiry, mac = parsed
    if link_id != link.id or expiry != int(link.expires_at.timestamp()) or now.timestamp() >= expiry:
        return False
    return hmac.compare_digest(mac, _mac(secret(settings), link.id, link.job_id, expiry))
