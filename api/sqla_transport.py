"""The server-less broker of the embedded mode: kombu's SQLAlchemy transport on SQLite, with three fixes.

kombu 5.x passes every transport option to ``create_engine``, so ``polling_interval`` (needed for a broker that
answers in well under a second) breaks it; it keeps every delivered message forever (``visible = False``); and
its SQLite connections have no busy timeout. This subclass removes the polling option before creating the
engine, deletes a message when it is delivered, and opens SQLite in WAL mode with a 30 s busy timeout.

Delivery semantics: a message is gone from the table once a worker took it, so a worker killed with -9 loses
the message it held; the reaper (worker/reaper.py) re-sends jobs from the database rows, which are the truth.
Registered under the URL scheme ``retarget-sqla+`` (see :func:`register`).
"""

from __future__ import annotations

import json
from queue import Empty
from typing import Any

from kombu.transport import TRANSPORT_ALIASES
from kombu.transport import sqlalchemy as kombu_sqla
from kombu.utils.encoding import bytes_to_str
from sqlalchemy import create_engine, event, text

ALIAS = "retarget-sqla"
_ENGINE_OPTION_BLOCKLIST = (
    "polling_interval",
    "queue_tablename",
    "message_tablename",
    "callback",
    "errback",
    "max_retries",
    "interval_start",
    "interval_step",
    "interval_max",
    "retry_errors",
    "visibility_timeout",
)


def _pragmas(dbapi_connection: Any, _record: Any) -> None:
    cur = dbapi_connection.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


class Channel(kombu_sqla.Channel):
    """kombu's SQLAlchemy channel with engine options filtered and messages deleted on delivery."""

    def _engine_from_config(self) -> Any:
        conninfo = self.connection.client
        options = {k: v for k, v in conninfo.transport_options.items() if k not in _ENGINE_OPTION_BLOCKLIST}
        url = conninfo.hostname
        if url.startswith("sqlite"):
            options.setdefault("connect_args", {"timeout": 30, "check_same_thread": False})
            engine = create_engine(url, **options)
            event.listen(engine, "connect", _pragmas)
            return engine
        return create_engine(url, **options)

    def _get(self, queue: str, timeout: Any = None) -> Any:
        obj = self._get_or_create(queue)
        if self.session.bind.name == "sqlite":
            self.session.execute(text("BEGIN IMMEDIATE TRANSACTION"))
        try:
            msg = (
                self.session.query(self.message_cls)
                .with_for_update()
                .filter(self.message_cls.queue_id == obj.id)
                .filter(self.message_cls.visible != False)  # noqa: E712 (SQL expression)
                .order_by(self.message_cls.sent_at)
                .order_by(self.message_cls.id)
                .limit(1)
                .first()
            )
            if msg is None:
                raise Empty()
            payload = json.loads(bytes_to_str(msg.payload))
            self.session.delete(msg)
            return payload
        finally:
            self.session.commit()


class Transport(kombu_sqla.Transport):
    """Transport registered as ``retarget-sqla``."""

    Channel = Channel


def register() -> None:
    """Make the URL scheme ``retarget-sqla+<sqlalchemy url>`` resolve to this transport (idempotent)."""
    TRANSPORT_ALIASES[ALIAS] = f"{__name__}:Transport"
