"""Benchmark of the service on this machine: API latency under concurrent clients, and job throughput.

Starts the service as separate processes (API under uvicorn, an io worker, cpu workers) on a temporary data
directory and SQLite database, with Redis (a spare database number, flushed) or the embedded SQLite broker.

1. API latency (p50/p95/p99, requests/s) with N concurrent clients for
   - status polls: GET /v1/jobs/{id};
   - job submissions: POST /v1/jobs. These jobs go to the ``gpu`` queue, which no worker here consumes, so the
     numbers are the API's own cost, not the cost of running jobs on the same two cores.
2. End-to-end throughput: J jobs (a shared clip, F frames, onto a shared character) submitted at once, timed
   from the first submission to the last job finished, with 1 and then 2 cpu worker processes.

    python benchmarks/bench/service_benchmark.py                      # defaults, writes benchmarks/bench/results/service.json
    python benchmarks/bench/service_benchmark.py --clients 1,8 --duration 3 --jobs 6 --broker embedded
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from api.db import session_scope
from api.migrate import upgrade
from api.security import create_key

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    REPO,
    add_output,
    claim_redis_db,
    free_port,
    machine,
    parser,
    percentiles,
    results_dir,
    service_env,
    shared_data,
    stop_group,
    write_json,
)


class Service:
    """The service's processes."""

    def __init__(self, root: Path, broker: str) -> None:
        self.root = root
        self.db_url = f"sqlite:///{root / 'service.sqlite'}"
        upgrade(self.db_url)
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.redis = None
        self.env = service_env(root, self.db_url, RETARGET_API_PAGE_SIZE_MAX="1000")
        if broker == "redis":
            self.redis, db = claim_redis_db()
            self.env["REDIS_URL"] = f"redis://127.0.0.1:6379/{db}"
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        (root / "logs").mkdir()
        with session_scope(self.db_url) as s:
            _, key = create_key(s, "benchmark")
        self.headers = {"X-API-Key": key}

    def start(self, name: str, args: list[str]) -> None:
        log = open(self.root / "logs" / f"{name}.log", "ab")  # noqa: SIM115
        self.procs[name] = subprocess.Popen([sys.executable, *args], cwd=REPO, env=self.env, stdout=log,
                                            stderr=subprocess.STDOUT, start_new_session=True)

    def start_worker(self, name: str, queues: str) -> None:
        self.start(name, ["-m", "worker", "--queues", queues, "--concurrency", "1", "--loglevel", "WARNING",
                          "--name", f"{name}@%h"])

    def start_api(self) -> None:
        self.start("api", ["-m", "uvicorn", "api.main:create_app", "--factory", "--port", str(self.port),
                           "--log-level", "warning", "--no-access-log"])

    def wait_ready(self, cpu_workers: int, timeout: float = 240.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                r = httpx.get(f"{self.base}/readyz", timeout=5, headers=self.headers)
                live = [w for w in r.json()["checks"]["workers"].get("live", []) if "cpu" in w["queues"]]
                if r.status_code == 200 and len(live) >= cpu_workers:
                    return
            except (httpx.HTTPError, KeyError, ValueError):
                pass
            time.sleep(0.5)
        raise SystemExit(f"service not ready; logs in {self.root / 'logs'}")

    def stop(self) -> None:
        for p in self.procs.values():
            stop_group(p)
        if self.redis is not None:
            self.redis.flushdb()


def load(base: str, headers: dict[str, str], clients: int, duration: float, request: Any) -> dict[str, Any]:
    """``clients`` threads, each with its own connection, calling ``request(client)`` for ``duration`` s."""
    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors = [0] * clients
    start_barrier = threading.Barrier(clients)

    def run(i: int) -> None:
        with httpx.Client(base_url=base, headers=headers, timeout=30) as c:
            request(c)  # warm the connection
            start_barrier.wait()
            end = time.perf_counter() + duration
            while time.perf_counter() < end:
                t = time.perf_counter()
                ok = request(c)
                latencies[i].append(time.perf_counter() - t)
                errors[i] += 0 if ok else 1

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    flat = [x for per in latencies for x in per]
    lat = {k: v for k, v in percentiles(flat, digits=2).items() if k != "max_ms"}
    return {"clients": clients, **lat, "requests_per_s": round(len(flat) / duration, 1),
            "errors": sum(errors), "wall_s": round(wall, 2)}


def wait_jobs(http: httpx.Client, ids: list[str], timeout: float) -> list[dict[str, Any]]:
    deadline = time.monotonic() + timeout
    pending = set(ids)
    done: dict[str, dict[str, Any]] = {}
    while pending and time.monotonic() < deadline:
        for job_id in list(pending):
            j = http.get(f"/v1/jobs/{job_id}").json()
            if j["status"] in ("succeeded", "failed", "canceled"):
                done[job_id] = j
                pending.discard(job_id)
        time.sleep(0.2)
    if pending:
        raise SystemExit(f"{len(pending)} jobs not finished after {timeout} s")
    return [done[i] for i in ids]


def throughput(svc: Service, http: httpx.Client, motion: str, character: str, workers: int, jobs: int,
               opts: dict[str, Any]) -> dict[str, Any]:  # fmt: skip
    """``jobs`` jobs submitted at once with ``workers`` cpu worker processes (a second one started here), timed
    from the first submission to the last job finished."""
    if workers > len([n for n in svc.procs if n.startswith("cpu")]):
        svc.start_worker(f"cpu{workers}", "cpu")
        svc.wait_ready(workers)
    t0 = time.perf_counter()
    ids = [http.post("/v1/jobs", json={"motion_id": motion, "target_character_id": character,
                                       "options": opts}).json()["id"] for _ in range(jobs)]  # fmt: skip
    done = wait_jobs(http, ids, 1200)
    wall = time.perf_counter() - t0
    runs = [j["timings"]["run_seconds"] for j in done if j["timings"]["run_seconds"]]
    return {"workers": workers, "jobs": jobs, "succeeded": sum(j["status"] == "succeeded" for j in done),
            "wall_s": round(wall, 2), "jobs_per_min": round(60 * jobs / wall, 2),
            "mean_run_s": round(statistics.fmean(runs), 2) if runs else None,
            "workers_used": sorted({j["worker"] for j in done})}  # fmt: skip


def print_results(results: dict[str, Any], args: argparse.Namespace) -> None:
    print(f"\nService benchmark ({results['machine']['cpus']} CPUs, broker {args.broker}, SQLite)")
    for name in ("status_polls", "job_submissions"):
        print(f"\n{name.replace('_', ' ')}:  clients   p50 ms   p95 ms   p99 ms   req/s  errors")
        for r in results[name]:
            print(f"{'':>17}{r['clients']:>7} {r['p50_ms']:>8} {r['p95_ms']:>8} {r['p99_ms']:>8} "
                  f"{r['requests_per_s']:>7} {r['errors']:>7}")
    print(f"\nthroughput ({args.jobs} jobs x {args.frames} frames):  workers   wall s   jobs/min   mean run s")
    for r in results["throughput"]:
        print(f"{'':>40}{r['workers']:>7} {r['wall_s']:>8} {r['jobs_per_min']:>10} {r['mean_run_s']:>12}")


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--clients", default="1,4,16", help="concurrent clients, comma-separated")
    ap.add_argument("--duration", type=float, default=5.0, help="seconds per latency run")
    ap.add_argument("--jobs", type=int, default=8, help="jobs per throughput run")
    ap.add_argument("--frames", type=int, default=120, help="frames per job (frame_end)")
    ap.add_argument("--clip", default="motions/cmu/007_03.bvh", help="under the shared data directory")
    ap.add_argument("--character", default="characters/mh_male_bulky.glb")
    ap.add_argument("--broker", choices=("redis", "embedded"), default="redis")
    add_output(ap, results_dir("bench") / "service.json")
    args = ap.parse_args()
    data = shared_data()
    clients = [int(c) for c in args.clients.split(",")]
    results: dict[str, Any] = {
        "machine": machine(),
        "broker": args.broker, "database": "sqlite",
        "settings": {"duration_s": args.duration, "jobs": args.jobs, "frames": args.frames, "clip": args.clip,
                     "character": args.character},
    }
    with tempfile.TemporaryDirectory(prefix="retarget-bench-") as tmp:
        svc = Service(Path(tmp), args.broker)
        try:
            svc.start_worker("io", "io")
            svc.start_worker("cpu1", "cpu")
            svc.start_api()
            svc.wait_ready(1)
            headers = svc.headers
            http = httpx.Client(base_url=svc.base, headers=headers, timeout=120)
            with open(data / args.character, "rb") as fh:
                character = http.post("/v1/characters", files={"file": (Path(args.character).name, fh)}).json()["id"]
            with open(data / args.clip, "rb") as fh:
                motion = http.post("/v1/motions", files={"file": (Path(args.clip).name, fh)}).json()["id"]
            opts = {"frame_end": args.frames}
            probe = http.post("/v1/jobs", json={"motion_id": motion, "target_character_id": character,
                                                "options": opts}).json()["id"]
            wait_jobs(http, [probe], 300)

            # 1. API latency
            def poll(c: httpx.Client) -> bool:
                return c.get(f"/v1/jobs/{probe}").status_code == 200

            def submit(c: httpx.Client) -> bool:
                r = c.post("/v1/jobs", json={"motion_id": motion, "target_character_id": character,
                                             "options": opts, "queue": "gpu"})
                return r.status_code == 202

            results["status_polls"] = [load(svc.base, headers, n, args.duration, poll) for n in clients]
            results["job_submissions"] = [load(svc.base, headers, n, args.duration, submit) for n in clients]
            queued = http.get("/v1/jobs", params={"status": "queued", "limit": 1}).json()["total"]
            results["job_submissions_queued_on_gpu"] = queued

            results["throughput"] = [throughput(svc, http, motion, character, workers, args.jobs, opts)
                                     for workers in (1, 2)]  # fmt: skip
        finally:
            svc.stop()

    print_results(results, args)
    write_json(args.output, results)


if __name__ == "__main__":
    main()
