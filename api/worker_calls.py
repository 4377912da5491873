"""Ask a worker for something short and wait for the answer in the database (no Celery result backend).

The API writes a ``worker_calls`` row, sends the task by name with the row id, and polls the row until the
worker has written ``ok`` or ``error`` or the timeout passes.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from celery import Celery
from starlette.concurrency import run_in_threadpool

from api.db import session_scope
from api.models import WorkerCall


class WorkerUnavailable(Exception):
    """No worker answered in time, or the broker could not be reached."""


class WorkerCallFailed(Exception):
    """The worker answered with an error message meant for the user."""


def _create(url: str, op: str) -> str:
    with session_scope(url) as s:
        call = WorkerCall(op=op)
        s.add(call)
        s.flush()
        return call.id


def _read(url: str, call_id: str) -> tuple[str, dict[str, Any] | None, str | None]:
    with session_scope(url) as s:
        call = s.get(WorkerCall, call_id)
        if call is None:
            return "error", None, "the request record vanished"
        return call.status, call.result, call.message


async def call_worker(
    celery: Celery, database_url: str, task: str, kwargs: dict[str, Any], timeout: float
) -> dict[str, Any]:
    """Run ``task`` on a worker and return its result dict. Raises WorkerUnavailable or WorkerCallFailed."""
    call_id = await run_in_threadpool(_create, database_url, task)
    try:
        await run_in_threadpool(lambda: celery.send_task(task, kwargs={"call_id": call_id, **kwargs}))
    except Exception as exc:
        raise WorkerUnavailable(f"the task queue cannot be reached ({type(exc).__name__}: {exc})") from exc
    deadline = time.monotonic() + timeout
    delay = 0.02
    while True:
        status, result, message = await run_in_threadpool(_read, database_url, call_id)
        if status == "ok":
            return result or {}
        if status == "error":
            raise WorkerCallFailed(message or "the worker reported an error without a message")
        if time.monotonic() >= deadline:
            raise WorkerUnavailable(
                f"no worker answered within {timeout:.0f} s (setting RETARGET_API_INSPECT_TIMEOUT_SECONDS); "
                "check that a worker consuming the 'io' queue is running (GET /readyz)"
            )
        await asyncio.sleep(delay)
        delay = min(0.25, delay * 1.5)
