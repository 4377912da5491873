"""Run one job: claim the row, run the pipeline with progress, heartbeat and cancel checks, record the outcome.

Independent of Celery (the task in worker/tasks.py is a thin wrapper), so it can be tested directly. Every write
is conditional on (job id, attempt, status running): a run that lost its job to the reaper can write nothing.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from api.db import session_scope, updated, utcnow
from api.joblife import queue_webhook, settle_lost
from api.models import Asset, Job
from api.redact import redact
from api.settings import Settings
from api.storage import Storage
from retarget_core.jobs import OUTPUT_FILES

log = logging.getLogger(__name__)

OUTPUT_FIELDS = {name: field for field, name in OUTPUT_FILES.items()}  # file name -> JobOutputs field


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as None and unknown objects as strings (PostgreSQL JSON rejects NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if value is None or isinstance(value, (str, int, bool)):
        return value
    try:  # numpy / torch scalars
        return json_safe(value.item())
    except (AttributeError, ValueError):
        return str(value)


def blob_names(session: Any, job: Job) -> dict[str, str]:
    """sha256 -> the file name the job's owner gave each input (for messages)."""
    ids = [i for i in (job.motion_id, job.target_character_id, job.source_character_id) if i]
    rows = session.scalars(select(Asset).where(Asset.id.in_(ids))).all()
    return {a.sha256: a.filename or a.name for a in rows if a.sha256}


def pid_alive(pid: int) -> bool:
    """True when process ``pid`` exists on this machine and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


@dataclass
class RunResult:
    """How a run ended: ``skipped`` (not ours to run), ``lost`` (reaper took it), or the job's final status."""

    outcome: str
    webhook_delivery: str | None = None


class JobRun:
    """One attempt of one job inside a worker process."""

    def __init__(self, settings: Settings, job_id: str, attempt: int, hostname: str) -> None:
        self.settings = settings
        self.url = settings.resolved_database_url
        self.storage = Storage(settings.data_dir)
        self.job_id = job_id
        self.attempt = attempt
        self.hostname = hostname
        self.cancel_event = threading.Event()
        self.lost_event = threading.Event()
        self._stop = threading.Event()
        self._last_progress_write = 0.0
        self._last_stage: str | None = None
        self._last_cancel_check = 0.0
        self.lost_webhook: str | None = None
        self.blob_names: dict[str, str] = {}

    # Row updates ---------------------------------------------------------------------------------------------
    def _mine(self) -> tuple[Any, ...]:
        return (Job.id == self.job_id, Job.attempt == self.attempt, Job.status == "running")

    def claim(self) -> bool:
        """queued -> running for this attempt; False when the row is not queued at this attempt."""
        now = utcnow()
        with session_scope(self.url) as s:
            n = updated(s,
                update(Job)
                .where(Job.id == self.job_id, Job.attempt == self.attempt, Job.status == "queued")
                .values(status="running", stage="starting", progress=0.0, worker=self.hostname,
                        worker_pid=os.getpid(), started_at=now, heartbeat_at=now, updated_at=now)
            )
        return n == 1

    def take_over(self) -> bool:
        """When this attempt is 'running' but the process that ran it is gone, queue the job again as the next
        attempt (with a note saying so) and return True: this run then claims it.

        That happens when a pool child is killed: Celery redelivers its message at once, while the row still
        says running. On the same worker node the old process is checked directly; on another node this run
        waits (at most ``redelivery_takeover_seconds`` plus two heartbeats) for its heartbeat to go stale. A
        duplicate message of a run that is alive returns False."""
        patience = self.settings.redelivery_takeover_seconds + 2 * self.settings.heartbeat_interval_seconds
        deadline = time.monotonic() + patience
        while True:
            with session_scope(self.url) as s:
                row = s.execute(select(Job.status, Job.attempt, Job.worker, Job.worker_pid, Job.heartbeat_at)
                                .where(Job.id == self.job_id)).one_or_none()
            if row is None or row.status != "running" or row.attempt != self.attempt:
                return False
            same_node = row.worker == self.hostname and row.worker_pid is not None
            if same_node and row.worker_pid != os.getpid() and pid_alive(row.worker_pid):
                return False
            silent = (utcnow() - row.heartbeat_at).total_seconds() if row.heartbeat_at else float("inf")
            if same_node or silent >= self.settings.redelivery_takeover_seconds:
                return self._requeue_lost(row.worker_pid)
            if time.monotonic() >= deadline:
                return False
            time.sleep(min(1.0, self.settings.heartbeat_interval_seconds))

    def _requeue_lost(self, old_pid: int | None) -> bool:
        mine = (Job.id == self.job_id, Job.attempt == self.attempt, Job.status == "running", Job.worker_pid == old_pid)
        with session_scope(self.url) as s:
            job = s.get(Job, self.job_id)
            if job is None:
                return False
            lost = job.attempt
            outcome, self.lost_webhook = settle_lost(
                s, job, mine, utcnow(), self.settings.max_job_attempts, self.settings.job_hard_time_limit_seconds,
                "its worker process was killed or crashed", sent=True)
        if outcome != "queued":
            return False
        log.warning("job %s: attempt %s lost its process; running it again as attempt %s", self.job_id, lost, lost + 1)
        self.attempt = lost + 1
        return True

    def beat(self) -> None:
        """Refresh the heartbeat; notice a cancel request or a lost job."""
        now = utcnow()
        with session_scope(self.url) as s:
            n = updated(s, update(Job).where(*self._mine()).values(heartbeat_at=now))
            if n == 0:
                self.lost_event.set()
                self.cancel_event.set()
                return
            if s.scalar(select(Job.cancel_requested).where(Job.id == self.job_id)):
                self.cancel_event.set()

    def progress(self, stage: str, fraction: float) -> None:
        """The pipeline's progress callback (throttled writes; always on a stage change)."""
        now = time.monotonic()
        if (stage == self._last_stage and fraction < 1.0
                and now - self._last_progress_write < self.settings.progress_min_interval_seconds):
            return
        self._last_stage = stage
        self._last_progress_write = now
        frac = min(1.0, max(0.0, float(fraction))) if math.isfinite(fraction) else 0.0
        with session_scope(self.url) as s:
            n = updated(s, update(Job).where(*self._mine()).values(stage=stage[:64], progress=frac,
                                                                  updated_at=utcnow()))
        if n == 0:
            self.lost_event.set()
            self.cancel_event.set()

    def should_cancel(self) -> bool:
        """The pipeline's cancel check (reads the row at most every 0.5 s)."""
        if self.cancel_event.is_set():
            return True
        now = time.monotonic()
        if now - self._last_cancel_check >= 0.5:
            self._last_cancel_check = now
            with session_scope(self.url) as s:
                row = s.execute(select(Job.status, Job.attempt, Job.cancel_requested)
                                .where(Job.id == self.job_id)).one_or_none()
            if row is None or row.status != "running" or row.attempt != self.attempt:
                self.lost_event.set()
                self.cancel_event.set()
            elif row.cancel_requested:
                self.cancel_event.set()
        return self.cancel_event.is_set()

    def finish(self, status: str, **values: Any) -> RunResult:
        """Record the end of this run; queue the webhook in the same transaction."""
        now = utcnow()
        with session_scope(self.url) as s:
            n = updated(s,
                update(Job).where(*self._mine())
                .values(status=status, finished_at=now, updated_at=now, heartbeat_at=now, **values)
            )
            if n == 0:
                return RunResult("lost")
            job = s.get(Job, self.job_id)
            assert job is not None
            s.refresh(job)
            delivery = queue_webhook(s, job)
        return RunResult(status, delivery)

    # Heartbeat thread ----------------------------------------------------------------------------------------
    def _heartbeat_loop(self) -> None:
        while not self._stop.wait(self.settings.heartbeat_interval_seconds):
            try:
                self.beat()
            except Exception:
                log.exception("heartbeat of job %s failed", self.job_id)

    # The run -------------------------------------------------------------------------------------------------
    def inputs(self, job: Job) -> Any:
        from retarget_core.jobs import JobInputs
        from retarget_core.options import RetargetOptions

        def path_or_builtin(ref: str | None) -> Path | str | None:
            if ref is None or ref.startswith("builtin:"):
                return ref
            return self.storage.blob_path(ref)

        motion = path_or_builtin(job.motion_ref)
        target = path_or_builtin(job.target_ref)
        assert motion is not None and target is not None
        options = RetargetOptions.model_validate(job.options or {})
        if "device" not in (job.options or {}):
            options.device = self.settings.worker_device or ("cuda" if job.queue == "gpu" else "cpu")
        return JobInputs(motion_path=Path(motion), target=target, source_character=path_or_builtin(job.source_ref),
                         options=options)

    def run(self, pipeline: Callable[..., Any] | None = None) -> RunResult:
        """Claim and run; ``pipeline`` defaults to retarget_core.pipeline.run_job (tests pass their own)."""
        if not self.claim() and not (self.take_over() and self.claim()):
            log.info("job %s attempt %s is not queued: nothing to do", self.job_id, self.attempt)
            return RunResult("skipped", self.lost_webhook)
        hb = threading.Thread(target=self._heartbeat_loop, name=f"heartbeat-{self.job_id}", daemon=True)
        hb.start()
        try:
            return self._run(pipeline)
        finally:
            self._stop.set()
            hb.join(timeout=5)

    def _run(self, pipeline: Callable[..., Any] | None) -> RunResult:
        from celery.exceptions import SoftTimeLimitExceeded

        from retarget_core.errors import RetargetError
        from retarget_core.jobs import JobCanceled

        with session_scope(self.url) as s:
            job = s.get(Job, self.job_id)
            assert job is not None
            inputs = self.inputs(job)
            self.blob_names = blob_names(s, job)
        out_dir = self.storage.job_run_dir(self.job_id, self.attempt)
        try:
            if pipeline is None:
                from retarget_core.pipeline import run_job

                pipeline = run_job
            outputs = pipeline(inputs, out_dir, progress=self.progress, should_cancel=self.should_cancel)
        except JobCanceled:
            if self.lost_event.is_set():
                return RunResult("lost")
            return self.finish("canceled", message="canceled by the client", stage=self._last_stage)
        except RetargetError as exc:
            return self.finish("failed", message=self._clean(str(exc), inputs), error_kind="input")
        except SoftTimeLimitExceeded:
            return self.finish(
                "failed", error_kind="timeout",
                message=f"the job ran longer than {self.settings.job_soft_time_limit_seconds} s and was stopped "
                "(setting RETARGET_API_JOB_SOFT_TIME_LIMIT_SECONDS); try a shorter frame range",
            )
        except Exception as exc:
            log.error("job %s failed with an internal error:\n%s", self.job_id, traceback.format_exc())
            text = self._clean(f"{type(exc).__name__}: {exc}", inputs)
            return self.finish("failed", message=f"internal error: {text}"[:2000], error_kind="internal")
        if self.lost_event.is_set():
            return RunResult("lost")
        files: dict[str, str] = {}
        for name, attr in OUTPUT_FIELDS.items():
            p = getattr(outputs, attr, None)
            if p is None and (out_dir / name).is_file():
                p = out_dir / name
            if p is not None and Path(p).is_file():
                files[name] = self.storage.relative(Path(p))
        missing = [n for n in OUTPUT_FILES.values() if n != OUTPUT_FILES["source_glb"] and n not in files]
        if missing:
            return self.finish("failed", error_kind="internal",
                               message=f"internal error: the pipeline did not write {', '.join(missing)}")
        return self.finish(
            "succeeded", stage="done", progress=1.0, outputs=files,
            summary=json_safe(getattr(outputs, "summary", None) or {}),
            stage_seconds=json_safe(getattr(outputs, "stage_seconds", None) or {}),
            warnings=[self._clean(str(w), inputs) for w in (getattr(outputs, "warnings", None) or [])],
        )

    def _clean(self, text: str, inputs: Any) -> str:
        """Replace storage paths and blob names in a message by what the user knows the files as."""
        names = {inputs.motion_path: "the motion", inputs.target: "the target character",
                 inputs.source_character: "the source character"}
        for p, label in names.items():
            if isinstance(p, Path):
                text = text.replace(str(p), label)
        return redact(text, self.blob_names, "the file")
