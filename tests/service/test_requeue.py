"""A job whose pool process is killed is queued again at once, well before the heartbeat timeout.

Its own worker (real Redis, a real ``python -m worker`` process) with the DEFAULT heartbeat timeout (60 s), so the
reaper cannot be what restarts the job within the bound. Three kills in a row: from the second on, the message
Celery hands back names an older attempt than the one that ran, which once left the job waiting for the reaper.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from service_harness import REPO, PrivateRedis, Service, claim_clean_redis_db

from api.db import dispose_all, session_scope, utcnow
from api.migrate import upgrade
from api.models import Job, WorkerProcess
from api.queue import TASK_RUN_JOB, make_celery
from api.security import create_key
from api.settings import Settings
from api.storage import Storage

pytestmark = pytest.mark.service

REQUEUE_BOUND_S = 20.0
KILLS = 3


@pytest.fixture(scope="module")
def lone_worker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """A cpu worker on its own Redis and SQLite database, heartbeat settings left at their defaults."""
    root = tmp_path_factory.mktemp("requeue")
    private = PrivateRedis(root / "redis") if PrivateRedis.available() else None
    if private is not None:
        private.start()
        redis_url = private.url
    else:
        db, _ = claim_clean_redis_db()
        redis_url = f"redis://127.0.0.1:6379/{db}"
    url = f"sqlite:///{root / 'db.sqlite'}"
    upgrade(url)
    env = {k: v for k, v in os.environ.items() if not k.startswith("RETARGET_API_") and k != "DATABASE_URL"}
    env.update({"PYTHONPATH": str(REPO), "RETARGET_API_DATA_DIR": str(root / "data"), "REDIS_URL": redis_url,
                "RETARGET_API_DATABASE_URL": url, "RETARGET_API_MAX_JOB_ATTEMPTS": str(KILLS + 1),
                "OMP_NUM_THREADS": "1"})
    (root / "logs").mkdir()
    svc = Service("", root / "data", url, redis_url, env, root / "logs")
    try:
        svc.start_worker("cpu", "cpu")
        yield svc
    finally:
        svc.stop_all()
        dispose_all()
        if private is not None:
            private.stop()
        else:
            import redis

            redis.Redis.from_url(redis_url).flushdb()


def queued_job(settings: Settings, motion: Path, character: Path) -> str:
    """A queued job row (stored inputs, an owner key, marked sent so the reaper leaves it alone); its id."""
    storage = Storage(settings.data_dir)
    storage.ensure()
    refs = []
    for path, fmt in ((motion, "bvh"), (character, "glb")):
        tmp = storage.temp_path()
        shutil.copyfile(path, tmp)
        refs.append(storage.commit_blob(tmp, storage.blob_ref(hashlib.sha256(path.read_bytes()).hexdigest(), fmt))[0])
    with session_scope(settings.resolved_database_url) as s:
        key, _ = create_key(s, "requeue")
        job = Job(owner_id=key.id, motion_id="mot_x", target_character_id="chr_x", motion_ref=refs[0].name,
                  target_ref=refs[1].name, options={"fps": 30}, queue="cpu", status="queued", sent_at=utcnow())
        s.add(job)
        s.flush()
        return job.id


def wait_worker_ready(svc: Service, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with session_scope(svc.database_url) as s:
            if s.query(WorkerProcess).count():
                return
        time.sleep(0.2)
    raise AssertionError(f"the worker was not ready within {timeout} s\n{svc.log_tail()}")


def _row(url: str, job_id: str) -> Job:
    with session_scope(url) as s:
        job = s.get(Job, job_id)
        assert job is not None
        return job


def _running_pid(svc: Service, job_id: str, attempt: int, timeout: float = 180.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = _row(svc.database_url, job_id)
        if job.status == "running" and job.attempt == attempt and job.worker_pid:
            return job.worker_pid
        assert job.attempt <= attempt and job.status in ("queued", "running"), (job.status, job.attempt)
        time.sleep(0.05)
    raise AssertionError(f"attempt {attempt} did not run within {timeout} s\n{svc.log_tail()}")


def test_killed_pool_process_requeues_within_bound_with_default_heartbeat(lone_worker: Service, samples: Path
                                                                           ) -> None:
    svc = lone_worker
    settings = Settings(data_dir=svc.data_dir, database_url=svc.database_url, broker_url=svc.redis_url)
    assert settings.heartbeat_timeout_seconds > 2 * REQUEUE_BOUND_S  # the reaper alone would be too late
    job_id = queued_job(settings, samples / "motions" / "007_03.bvh", samples / "characters" / "mh_male_bulky.glb")
    wait_worker_ready(svc)  # its queue is declared: a message sent earlier could find no binding
    make_celery(settings).send_task(TASK_RUN_JOB, kwargs={"job_id": job_id, "attempt": 1}, queue="cpu")
    delays = []
    for attempt in range(1, KILLS + 1):
        pid = _running_pid(svc, job_id, attempt)
        time.sleep(0.5)
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        while _row(svc.database_url, job_id).attempt == attempt and time.monotonic() - killed < 2 * REQUEUE_BOUND_S:
            time.sleep(0.05)
        delays.append(time.monotonic() - killed)
        job = _row(svc.database_url, job_id)
        assert job.attempt == attempt + 1 and job.status in ("queued", "running"), (job.status, svc.log_tail())
        assert f"attempt {attempt} stopped" in (job.note or ""), job.note
    assert max(delays) < REQUEUE_BOUND_S, delays
    _running_pid(svc, job_id, KILLS + 1)  # and the last attempt runs
