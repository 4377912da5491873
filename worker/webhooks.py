"""Webhook delivery: POST the job as signed JSON to its callback URL; retried with exponential backoff.

Each attempt carries its number; an attempt runs only if the row is pending at the attempt before it, so a
duplicated message (re-sent by the reaper) never sends twice. Receivers should still treat the delivery id
(header ``X-Retarget-Delivery``) as the key for de-duplication.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from datetime import timedelta
from typing import Any

import httpx
from sqlalchemy import select, update

from api.db import session_scope, updated, utcnow
from api.models import ApiKey, Job, WebhookDelivery
from api.security import SIGNATURE_HEADER, sign_payload
from api.serialize import webhook_payload
from api.settings import Settings

log = logging.getLogger(__name__)


def backoff_seconds(settings: Settings, attempt: int) -> float:
    """Delay between attempt ``attempt`` (failed) and the next: base * 2**(attempt-1), capped."""
    return float(min(settings.webhook_backoff_max_seconds, settings.webhook_backoff_base_seconds * 2 ** (attempt - 1)))


def deliver(settings: Settings, delivery_id: str, attempt: int,
            post: Callable[..., Any] | None = None) -> tuple[str, float | None]:
    """Make attempt ``attempt``. Returns (outcome, delay before the next attempt or None); outcome is
    ``delivered``, ``retry``, ``failed`` or ``skipped`` (not this attempt's turn)."""
    url = settings.resolved_database_url
    with session_scope(url) as s:
        claimed = updated(s,
            update(WebhookDelivery)
            .where(WebhookDelivery.id == delivery_id, WebhookDelivery.status == "pending",
                   WebhookDelivery.attempts == attempt - 1)
            .values(attempts=attempt)
        )
        if not claimed:
            return "skipped", None
        d = s.get(WebhookDelivery, delivery_id)
        job = s.get(Job, d.job_id) if d else None
        if d is None or job is None:
            return "skipped", None
        key = s.scalar(select(ApiKey).where(ApiKey.id == job.owner_id))
        secret = settings.webhook_secret or (key.webhook_secret if key else "")
        body = json.dumps(webhook_payload(job, d, settings.public_base_url or ""), separators=(",", ":")).encode()
        target = d.url
        event = d.event
    headers = {
        "Content-Type": "application/json",
        "User-Agent": "retarget-webhook/1",
        "X-Retarget-Event": event,
        "X-Retarget-Delivery": delivery_id,
        "X-Retarget-Attempt": str(attempt),
        SIGNATURE_HEADER: sign_payload(secret, body),
    }
    code: int | None = None
    error: str | None = None
    try:
        sender = post or httpx.post
        response = sender(target, content=body, headers=headers, timeout=settings.webhook_timeout_seconds,
                          follow_redirects=False)
        code = response.status_code
        if not 200 <= code < 300:
            error = f"HTTP {code}"
    except Exception as exc:  # connection refused, timeout, bad URL ...
        error = f"{type(exc).__name__}: {exc}"[:500]
    now = utcnow()
    with session_scope(url) as s:
        d = s.get(WebhookDelivery, delivery_id)
        assert d is not None
        d.last_status_code = code
        d.last_error = error
        if error is None:
            d.status = "delivered"
            d.delivered_at = now
            return "delivered", None
        if attempt >= settings.webhook_max_attempts:
            d.status = "failed"
            log.warning("webhook %s to %s failed after %s attempts: %s", delivery_id, target, attempt, error)
            return "failed", None
        delay = backoff_seconds(settings, attempt)
        d.next_attempt_at = now + timedelta(seconds=delay)
        return "retry", delay
