"""Webhook delivery: POST the job as signed JSON to its callback URL; retried with exponential backoff.

The URL is checked again here, after DNS resolution (api.callbacks): only public addresses unless the host is
allowed by the setting ``callback_allowed_hosts``; the request goes to the checked address (Host header and TLS
server name are the URL's host), redirects are not followed, and the timeouts are short. What a failure records
is a category (refused, unreachable, timed out, HTTP status), never the remote's own error text.

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
from urllib.parse import urlsplit

import httpx
from sqlalchemy import select, update

from api.callbacks import CallbackRefused, resolve
from api.db import session_scope, updated, utcnow
from api.models import ApiKey, Job, WebhookDelivery
from api.security import SIGNATURE_HEADER, sign_payload
from api.serialize import webhook_payload
from api.settings import Settings

log = logging.getLogger(__name__)


def backoff_seconds(settings: Settings, attempt: int) -> float:
    """Delay between attempt ``attempt`` (failed) and the next: base * 2**(attempt-1), capped."""
    return float(min(settings.webhook_backoff_max_seconds, settings.webhook_backoff_base_seconds * 2 ** (attempt - 1)))


def _post(settings: Settings, url: str, body: bytes, headers: dict[str, str],
          post: Callable[..., Any] | None) -> tuple[int | None, str | None]:
    """One POST to a checked address; (status code, error category or None when delivered)."""
    try:
        target = resolve(url, settings.callback_allowed_hosts)
    except CallbackRefused as exc:
        return None, str(exc)
    timeout = httpx.Timeout(settings.webhook_timeout_seconds, connect=settings.webhook_connect_timeout_seconds)
    extensions = {"sni_hostname": target.host} if url.startswith("https:") else {}
    try:
        sender = post or _httpx_post
        response = sender(target.url, content=body, headers={**headers, "Host": _host_header(url)},
                          timeout=timeout, extensions=extensions)
    except httpx.TimeoutException:
        return None, "timed out"
    except httpx.ConnectError:
        return None, "could not connect"
    except Exception:  # TLS, protocol or anything else: never the remote's own words
        return None, "the delivery failed (network or TLS error)"
    code = response.status_code
    if 300 <= code < 400:
        return code, f"HTTP {code} (redirects are not followed)"
    if not 200 <= code < 300:
        return code, f"HTTP {code}"
    return code, None


def _httpx_post(url: str, *, content: bytes, headers: dict[str, str], timeout: httpx.Timeout,
                extensions: dict[str, Any]) -> httpx.Response:
    with httpx.Client(timeout=timeout, follow_redirects=False, trust_env=False) as client:
        return client.post(url, content=content, headers=headers, extensions=extensions)


def _host_header(url: str) -> str:
    parts = urlsplit(url)
    return parts.netloc.rsplit("@", 1)[-1]


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
    code, error = _post(settings, target, body, headers, post)
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
