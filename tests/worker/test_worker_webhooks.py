"""Webhook delivery to a local HTTP server: signature, retries with backoff, give-up, no double sends."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
from worker_testkit import add_job

from api.db import session_scope
from api.models import ApiKey, Job, WebhookDelivery
from api.security import SIGNATURE_HEADER, verify_signature
from api.settings import Settings
from worker.webhooks import backoff_seconds, deliver


class Hook:
    """A local receiver; answers the status codes in ``codes`` in turn (then 200)."""

    def __init__(self) -> None:
        self.received: list[tuple[dict[str, str], bytes]] = []
        self.codes: list[int] = []
        hook = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                hook.received.append(({k: v for k, v in self.headers.items()}, body))
                code = hook.codes.pop(0) if hook.codes else 200
                self.send_response(code)
                self.end_headers()

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()


@pytest.fixture
def hook() -> Iterator[Hook]:
    h = Hook()
    yield h
    h.server.shutdown()


def delivery(settings: Settings, url: str) -> tuple[str, str]:
    job_id = add_job(settings, callback_url=url)
    with session_scope(settings.resolved_database_url) as s:
        job = s.get(Job, job_id)
        job.status, job.message = "failed", "the motion: bad"
        d = WebhookDelivery(job_id=job_id, event="job.failed", url=url)
        s.add(d)
        s.flush()
        secret = s.get(ApiKey, job.owner_id).webhook_secret
        return d.id, secret


def test_delivery_is_signed_with_the_keys_secret(wsettings: Settings, hook: Hook) -> None:
    d_id, secret = delivery(wsettings, hook.url)
    assert deliver(wsettings, d_id, 1) == ("delivered", None)
    headers, body = hook.received[0]
    assert verify_signature(secret, body, headers[SIGNATURE_HEADER])
    assert not verify_signature("wrong", body, headers[SIGNATURE_HEADER])
    payload = json.loads(body)
    assert payload["event"] == "job.failed" and payload["delivery_id"] == d_id
    assert payload["job"]["status"] == "failed" and payload["job"]["message"] == "the motion: bad"
    assert headers["X-Retarget-Delivery"] == d_id and headers["Content-Type"] == "application/json"
    with session_scope(wsettings.resolved_database_url) as s:
        d = s.get(WebhookDelivery, d_id)
        assert d.status == "delivered" and d.attempts == 1 and d.last_status_code == 200
    # the same attempt again (a duplicate message) sends nothing
    assert deliver(wsettings, d_id, 1) == ("skipped", None) and len(hook.received) == 1


def test_failures_are_retried_with_backoff_then_given_up(wsettings: Settings, hook: Hook) -> None:
    wsettings.webhook_max_attempts = 3
    d_id, _ = delivery(wsettings, hook.url)
    hook.codes = [500, 503, 500]
    assert deliver(wsettings, d_id, 1) == ("retry", backoff_seconds(wsettings, 1))
    assert deliver(wsettings, d_id, 2) == ("retry", backoff_seconds(wsettings, 2))
    assert deliver(wsettings, d_id, 3) == ("failed", None)
    assert len(hook.received) == 3
    with session_scope(wsettings.resolved_database_url) as s:
        d = s.get(WebhookDelivery, d_id)
        assert d.status == "failed" and d.last_status_code == 500 and d.last_error == "HTTP 500"


def test_unreachable_receiver_is_retried(wsettings: Settings) -> None:
    d_id, _ = delivery(wsettings, "http://127.0.0.1:1/nothing-listens")
    outcome, delay = deliver(wsettings, d_id, 1)
    assert outcome == "retry" and delay == wsettings.webhook_backoff_base_seconds
    with session_scope(wsettings.resolved_database_url) as s:
        d = s.get(WebhookDelivery, d_id)
        assert d.status == "pending" and d.last_status_code is None and d.last_error == "could not connect"
        assert d.next_attempt_at is not None


def test_global_secret_setting_overrides(wsettings: Settings, hook: Hook) -> None:
    wsettings.webhook_secret = "global-secret"
    d_id, _ = delivery(wsettings, hook.url)
    deliver(wsettings, d_id, 1)
    headers, body = hook.received[0]
    assert verify_signature("global-secret", body, headers[SIGNATURE_HEADER])


def test_backoff_doubles_and_is_capped() -> None:
    s = Settings(webhook_backoff_base_seconds=2, webhook_backoff_max_seconds=20)
    assert [backoff_seconds(s, n) for n in range(1, 6)] == [2, 4, 8, 16, 20]


def test_private_addresses_are_refused_at_delivery_without_connecting(wsettings: Settings, hook: Hook) -> None:
    d_id, _ = delivery(wsettings, hook.url)
    wsettings.callback_allowed_hosts = []  # the receiver is on 127.0.0.1: no longer allowed
    outcome, _ = deliver(wsettings, d_id, 1)
    assert outcome == "retry" and hook.received == []
    with session_scope(wsettings.resolved_database_url) as s:
        d = s.get(WebhookDelivery, d_id)
        assert "not a public address" in d.last_error and d.last_status_code is None


def test_redirects_are_not_followed(wsettings: Settings, hook: Hook) -> None:
    d_id, _ = delivery(wsettings, hook.url)
    hook.codes = [302]
    assert deliver(wsettings, d_id, 1)[0] == "retry" and len(hook.received) == 1
    with session_scope(wsettings.resolved_database_url) as s:
        assert s.get(WebhookDelivery, d_id).last_error == "HTTP 302 (redirects are not followed)"
