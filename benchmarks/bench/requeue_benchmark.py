"""How soon a job whose worker pool process is killed (SIGKILL) is queued again, over repeated kills.

Real parts: a private redis-server, a SQLite database, one ``python -m worker --queues cpu`` process with the
default heartbeat settings, and a real job (a sample clip on a sample body). The job is allowed many attempts;
each round waits until an attempt runs, kills that attempt's pool process, and times until the row is queued
(or running) again as the next attempt. Writes benchmarks/bench/results/requeue_benchmark.json.

    flock /tmp/heavy.lock .venv/bin/python benchmarks/bench/requeue_benchmark.py --kills 20
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import select

from api.db import dispose_all, session_scope, utcnow
from api.migrate import upgrade
from api.models import Asset, Job, WorkerProcess, new_id
from api.queue import TASK_RUN_JOB, make_celery
from api.security import create_key
from api.settings import Settings
from api.storage import Storage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    REPO,
    SAMPLES,
    add_output,
    free_port,
    machine,
    parser,
    results_dir,
    service_env,
    stop_group,
    write_json,
)


def start_redis(root: Path) -> tuple[subprocess.Popen[bytes], str]:
    """A private redis-server on a free port; its process and URL."""
    import redis

    port = free_port()
    proc = subprocess.Popen(["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(root),
                             "--save", "", "--appendonly", "no"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 20
    while True:
        try:
            redis.Redis("127.0.0.1", port, socket_timeout=1).ping()
            return proc, f"redis://127.0.0.1:{port}/0"
        except redis.RedisError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def store(storage: Storage, path: Path, fmt: str) -> tuple[str, str]:
    """Copy a file into the blob store; its sha256 and blob reference."""
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    tmp = storage.temp_path()
    shutil.copyfile(path, tmp)
    ref = storage.blob_ref(sha, fmt)
    storage.commit_blob(tmp, ref)
    return sha, ref


def make_job(url: str, storage: Storage) -> str:
    """A queued job row (the sample walk on the bulky sample body) with its assets; its id."""
    storage.ensure()
    m_sha, m_ref = store(storage, SAMPLES / "motions" / "007_03.bvh", "bvh")
    c_sha, c_ref = store(storage, SAMPLES / "characters" / "mh_male_bulky.glb", "glb")
    with session_scope(url) as s:
        key, _ = create_key(s, "requeue-benchmark")
        s.flush()
        motion = Asset(id=new_id("mot"), kind="motion", owner_id=key.id, origin="upload", name="walk", filename="007_03.bvh",
                       format="bvh", sha256=m_sha, size_bytes=1, info={})
        body = Asset(id=new_id("chr"), kind="character", owner_id=key.id, origin="upload", name="bulky", filename="bulky.glb",
                     format="glb", sha256=c_sha, size_bytes=1, info={})
        s.add_all([motion, body])
        s.flush()
        job = Job(owner_id=key.id, motion_id=motion.id, target_character_id=body.id, motion_ref=m_ref,
                  target_ref=c_ref, options={"fps": 30}, queue="cpu", status="queued",
                  sent_at=utcnow())  # sent below: the reaper leaves it alone
        s.add(job)
        s.flush()
        return job.id


def row(url: str, job_id: str) -> Any:
    with session_scope(url) as s:
        return s.execute(select(Job.status, Job.attempt, Job.worker_pid, Job.note).where(Job.id == job_id)).one()


def wait_ready(url: str, timeout: float) -> None:
    """Until a worker has registered itself."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with session_scope(url) as s:
            if s.scalar(select(WorkerProcess.hostname).limit(1)):
                return
        time.sleep(0.2)
    raise TimeoutError(f"no worker ready after {timeout} s")


def wait_running(url: str, job_id: str, attempt: int, timeout: float) -> int:
    """The pool process id once ``attempt`` runs; TimeoutError otherwise."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r = row(url, job_id)
        if r.status == "running" and r.attempt == attempt and r.worker_pid:
            return int(r.worker_pid)
        if r.attempt > attempt or r.status in ("succeeded", "failed", "canceled"):
            raise RuntimeError(f"attempt {attempt} never ran: {r}")
        time.sleep(0.05)
    raise TimeoutError(f"attempt {attempt} not running after {timeout} s")


def time_requeue(url: str, job_id: str, attempt: int, pid: int, timeout: float) -> dict[str, float | None]:
    """Kill the pool process of ``attempt``; seconds until the row is at the next attempt (queued or later) and
    until that attempt runs."""
    os.kill(pid, signal.SIGKILL)
    killed = time.monotonic()
    queued_s = running_s = None
    while time.monotonic() - killed < timeout:
        r = row(url, job_id)
        if r.attempt > attempt and queued_s is None:
            queued_s = time.monotonic() - killed
        if r.attempt > attempt and r.status != "queued":
            running_s = time.monotonic() - killed
            break
        time.sleep(0.05)
    return {"queued_s": queued_s, "running_s": running_s}


def run(kills: int, timeout: float) -> dict[str, Any]:
    root = Path(tempfile.mkdtemp(prefix="requeue-bench-"))
    redis_proc, redis_url = start_redis(root)
    worker: subprocess.Popen[bytes] | None = None
    rounds: list[dict[str, Any]] = []
    try:
        url = f"sqlite:///{root / 'bench.sqlite'}"
        upgrade(url)
        job_id = make_job(url, Storage(root / "data"))
        env = service_env(root, url, REDIS_URL=redis_url, RETARGET_API_MAX_JOB_ATTEMPTS=str(kills + 1))
        with open(root / "worker.log", "wb") as log:
            worker = subprocess.Popen([sys.executable, "-m", "worker", "--queues", "cpu", "--concurrency", "1"],
                                      cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        wait_ready(url, 180)  # its queue is declared: a message sent earlier could find no binding
        make_celery(Settings(broker_url=redis_url)).send_task(TASK_RUN_JOB, kwargs={"job_id": job_id, "attempt": 1},
                                                              queue="cpu")
        for attempt in range(1, kills + 1):
            pid = wait_running(url, job_id, attempt, 180)
            time.sleep(1.0)  # the attempt is under way (past its claim)
            took = time_requeue(url, job_id, attempt, pid, timeout)
            rounds.append({"attempt": attempt, **took})
            print(f"kill {attempt}: queued again after {took['queued_s']} s, running after {took['running_s']} s",
                  flush=True)
            if took["queued_s"] is None:
                break
    finally:
        if worker is not None:
            stop_group(worker)
        redis_proc.terminate()
        redis_proc.wait(10)
        dispose_all()
    settings = Settings()
    delays = [r["queued_s"] for r in rounds if r["queued_s"] is not None]
    return {
        "what": "seconds from SIGKILL of a job's pool process to its row being queued again (next attempt)",
        "command": f"flock /tmp/heavy.lock .venv/bin/python benchmarks/bench/requeue_benchmark.py --kills {kills}",
        "date": datetime.now(UTC).strftime("%Y-%m-%d"),
        "heartbeat_timeout_seconds": settings.heartbeat_timeout_seconds,
        "kills": kills,
        "requeued": len(delays),
        "queued_max_s": max(delays) if delays else None,
        "queued_median_s": statistics.median(delays) if delays else None,
        "running_max_s": max((r["running_s"] for r in rounds if r["running_s"] is not None), default=None),
        "rounds": rounds,
    }


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--timeout", type=float, default=120.0, help="give up on one kill after this long")
    add_output(ap, results_dir("bench") / "requeue_benchmark.json")
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # clean up the worker and Redis when stopped
    result = run(args.kills, args.timeout)
    print(json.dumps({k: v for k, v in result.items() if k != "rounds"}, indent=2))
    write_json(args.output, {**result, "machine": machine()})


if __name__ == "__main__":
    main()
