"""Routes that end their database transaction in the thread that ran them.

A sync endpoint runs in a worker thread, and FastAPI then validates its return value in *another* thread. If
the request's session still held a connection while it waited for that second thread, 40 busy threads could
each wait for a connection held by a request waiting for a thread: the pool starves with the CPU idle. So every
sync endpoint commits (or rolls back) its sessions before it returns, and holds no connection afterwards.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any

from fastapi.routing import APIRoute
from sqlalchemy.orm import Session


def ends_transaction(func: Callable[..., Any]) -> Callable[..., Any]:
    """``func`` with every Session argument committed after it returns (rolled back when it raises)."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        sessions = [v for v in kwargs.values() if isinstance(v, Session)]
        try:
            result = func(*args, **kwargs)
        except BaseException:
            for s in sessions:
                s.rollback()
            raise
        for s in sessions:
            s.commit()
        return result

    return wrapper


class SessionRoute(APIRoute):
    """An APIRoute whose sync endpoint ends its transaction before returning (see the module docstring)."""

    def __init__(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        if not inspect.iscoroutinefunction(endpoint):
            endpoint = ends_transaction(endpoint)
        super().__init__(path, endpoint, **kwargs)
