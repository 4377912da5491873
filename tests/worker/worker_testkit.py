"""Helpers of the worker tests: a recording Celery stand-in and job rows with stored inputs."""

from __future__ import annotations

import hashlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from api.db import session_scope
from api.models import Job
from api.security import create_key
from api.settings import Settings
from api.storage import Storage


@dataclass
class Recorder:
    """Stands in for the Celery app: records send_task calls."""

    sent: list[tuple[str, dict[str, Any], str | None, float | None]] = field(default_factory=list)

    def send_task(self, name: str, kwargs: dict[str, Any] | None = None, queue: str | None = None,
                  countdown: float | None = None, **_: Any) -> None:
        self.sent.append((name, dict(kwargs or {}), queue, countdown))


def store(settings: Settings, path: Path) -> str:
    """Copy a file into the blob store; returns its reference."""
    from retarget_core.io.formats import detect_format

    storage = Storage(settings.data_dir)
    data = path.read_bytes()
    ref = storage.blob_ref(hashlib.sha256(data).hexdigest(), detect_format(path))
    tmp = storage.temp_path()
    shutil.copyfile(path, tmp)
    storage.commit_blob(tmp, ref)
    return ref


def add_job(settings: Settings, motion_ref: str = "0" * 64 + ".bvh", target_ref: str = "builtin:male_average",
            **values: Any) -> str:
    """A queued job row (and its owner key); returns the job id."""
    with session_scope(settings.resolved_database_url) as s:
        key, _ = create_key(s, "test")
        job = Job(owner_id=key.id, motion_id="mot_x", target_character_id="chr_x", motion_ref=motion_ref,
                  target_ref=target_ref, options=values.pop("options", {}), queue="cpu", status="queued", **values)
        s.add(job)
        s.flush()
        return job.id
