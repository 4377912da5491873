"""Load benchmark of the API: many concurrent pollers and submitters, on SQLite and on PostgreSQL.

Starts the API under uvicorn (``--api-processes``, default 2: one per core; Redis broker on a spare database number, flushed) on a temporary data
directory, with a motion, a character and one finished job written straight into the database, and no worker
(submitted jobs go to the ``gpu`` queue; nothing runs them, so the figures are the API's own cost). The load
generator is a small asyncio HTTP/1.1 client (one keep-alive connection per client), light enough to share the
machine with the API.

For every database and every level it prints p50/p95/p99 latency, requests/s and errors:
- ``poll``: N clients calling GET /v1/jobs/{id} as fast as they can;
- ``submit``: N clients calling POST /v1/jobs as fast as they can, each with its own key (the default
  per-key quota of queued jobs applies; nothing runs them, so a key's queue only grows);
- ``mixed``: 200 pollers and 64 submitters at once (the target: 0 errors, p99 under 1 s).

    python benchmarks/bench/load_benchmark.py                       # writes benchmarks/bench/results/load.json
    python benchmarks/bench/load_benchmark.py --databases sqlite --duration 5 --pollers 50,200 --submitters 64
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from api.db import dispose_all, session_scope
from api.migrate import upgrade
from api.models import Asset, Job
from api.security import create_key

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    REPO,
    add_output,
    claim_redis_db,
    free_port,
    machine,
    percentiles,
    results_dir,
    service_env,
    stop_group,
    write_json,
)

PG_ADMIN = os.environ.get("RETARGET_TEST_PG_ADMIN", "postgresql://postgres@127.0.0.1:5432/test")
TIMEOUT_S = 30.0


def make_database(kind: str, root: Path) -> tuple[str, Any]:
    if kind == "sqlite":
        return f"sqlite:///{root / 'service.sqlite'}", None
    import psycopg

    name = f"retarget_load_{secrets.token_hex(4)}"
    with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')

    def drop() -> None:
        dispose_all()
        with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    return PG_ADMIN.rsplit("/", 1)[0] + f"/{name}", drop


def seed(url: str, submitters: int) -> tuple[str, str, str, str, list[tuple[str, str, str]]]:
    """A key, a motion, a character and a finished job, and for each submitter its own key with a motion and a
    character (a client per key: the default per-key quota of queued jobs holds); returns (key, motion id,
    character id, job id, [(key, motion id, character id) per submitter])."""
    clients = []
    with session_scope(url) as s:
        for i in range(submitters):
            row, plain = create_key(s, f"submitter-{i}")
            s.add_all([
                Asset(id=f"mot_load{i}", kind="motion", owner_id=row.id, name="walk", filename="walk.bvh",
                      format="bvh", sha256="a" * 64, size_bytes=1000,
                      info={"frames": 120, "fps": 30.0, "duration_s": 4.0}),
                Asset(id=f"chr_load{i}", kind="character", owner_id=row.id, name="body", filename="body.glb",
                      format="glb", sha256="b" * 64, size_bytes=1000, info={"vertices": 10000})])
            clients.append((plain, f"mot_load{i}", f"chr_load{i}"))
        key_row, key = create_key(s, "load")
        motion = Asset(id="mot_load", kind="motion", owner_id=key_row.id, name="walk", filename="walk.bvh",
                       format="bvh", sha256="a" * 64, size_bytes=1000,
                       info={"frames": 120, "fps": 30.0, "duration_s": 4.0})
        character = Asset(id="chr_load", kind="character", owner_id=key_row.id, name="body", filename="body.glb",
                          format="glb", sha256="b" * 64, size_bytes=1000, info={"vertices": 10000})
        s.add_all([motion, character])
        s.flush()
        job = Job(owner_id=key_row.id, motion_id=motion.id, target_character_id=character.id,
                  motion_ref=f"{'a' * 64}.bvh", target_ref=f"{'b' * 64}.glb", status="succeeded", stage="done",
                  progress=1.0, outputs={"result.glb": "jobs/x/result.glb"})
        s.add(job)
        s.flush()
        return key, motion.id, character.id, job.id, clients


class Client:
    """One keep-alive HTTP/1.1 connection; ``request`` returns the status code (or raises)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def request(self, raw: bytes) -> int:
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection("127.0.0.1", self.port)
        assert self.reader is not None
        self.writer.write(raw)
        head = await self.reader.readuntil(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        length = 0
        close = False
        for line in lines[1:]:
            name, _, value = line.partition(":")
            if name.lower() == "content-length":
                length = int(value)
            elif name.lower() == "connection" and value.strip().lower() == "close":
                close = True
        if length:
            await self.reader.readexactly(length)
        if close:
            self.close()
        return status

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None


def get_request(path: str, key: str) -> bytes:
    return f"GET {path} HTTP/1.1\r\nHost: bench\r\nX-API-Key: {key}\r\n\r\n".encode()


def post_request(path: str, key: str, body: dict[str, Any]) -> bytes:
    data = json.dumps(body).encode()
    return (f"POST {path} HTTP/1.1\r\nHost: bench\r\nX-API-Key: {key}\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(data)}\r\n\r\n").encode() + data


async def client_loop(port: int, raw: bytes, ok: int, end: float, out: list[float], errors: list[str]) -> None:
    c = Client(port)
    while time.perf_counter() < end:
        t = time.perf_counter()
        try:
            status = await asyncio.wait_for(c.request(raw), TIMEOUT_S)
            if status != ok:
                errors.append(f"HTTP {status}")
        except Exception as exc:
            errors.append(type(exc).__name__)
            c.close()
            await asyncio.sleep(0.05)
        out.append(time.perf_counter() - t)
    c.close()


def summary(samples: list[float], errors: list[str], duration: float, clients: int) -> dict[str, Any]:
    """One group's latencies (p50/p95/p99/max), requests/s and errors by kind."""
    kinds: dict[str, int] = {}
    for e in errors:
        kinds[e] = kinds.get(e, 0) + 1
    lat = percentiles(samples)
    return {"clients": clients, "requests": lat.pop("n"), **lat, "requests_per_s": round(len(samples) / duration, 1),
            "errors": len(errors), "error_kinds": kinds}  # fmt: skip


Requests = bytes | list[bytes]  # one request for every client, or one per client (cycled)


async def run_level(port: int, groups: dict[str, tuple[int, Requests, int]], duration: float) -> dict[str, Any]:
    """Run every group (name -> (clients, request(s), expected status)) at once for ``duration`` seconds."""
    end = time.perf_counter() + duration
    samples: dict[str, list[float]] = {name: [] for name in groups}
    errors: dict[str, list[str]] = {name: [] for name in groups}
    tasks = [asyncio.create_task(client_loop(port, raw if isinstance(raw, bytes) else raw[i % len(raw)], ok, end,
                                             samples[name], errors[name]))
             for name, (n, raw, ok) in groups.items() for i in range(n)]
    await asyncio.gather(*tasks)
    return {name: summary(samples[name], errors[name], duration, groups[name][0]) for name in groups}


def start_api(root: Path, db_url: str, redis_db: int, port: int, processes: int = 1) -> subprocess.Popen[bytes]:
    env = service_env(root, db_url, REDIS_URL=f"redis://127.0.0.1:6379/{redis_db}")
    log = open(root / "api.log", "ab")  # noqa: SIM115
    return subprocess.Popen([sys.executable, "-m", "uvicorn", "api.main:create_app", "--factory", "--port", str(port),
                             "--log-level", "warning", "--no-access-log", "--backlog", "4096",
                             "--workers", str(processes)],
                            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def bench_database(kind: str, args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="retarget-load-") as tmp:
        root = Path(tmp) if not args.keep else Path(tempfile.mkdtemp(prefix="retarget-load-keep-"))
        url, drop = make_database(kind, root)
        redis, redis_db = claim_redis_db()
        api = None
        try:
            upgrade(url)
            key, _, _, job, clients = seed(url, max([*args.submitters, args.mixed_submitters]))
            dispose_all()
            port = free_port()
            api = start_api(root, url, redis_db, port, args.api_processes)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                        break
                except httpx.HTTPError:
                    time.sleep(0.3)
            poll = get_request(f"/v1/jobs/{job}", key)
            submit = [post_request("/v1/jobs", k, {"motion_id": m, "target_character_id": c,
                                                   "options": {"frame_end": 60}, "queue": "gpu"})
                      for k, m, c in clients]
            levels: list[dict[str, Any]] = []

            def run(groups: dict[str, tuple[int, Requests, int]]) -> None:
                asyncio.run(run_level(port, {k: v for k, v in groups.items() if v[0]}, 1.0))  # warm-up
                result = asyncio.run(run_level(port, {k: v for k, v in groups.items() if v[0]}, args.duration))
                levels.append(result)
                for name, r in result.items():
                    print(f"  {kind:<10} {name:<7} {r['clients']:>5} clients  p50 {r['p50_ms']:>7} ms  "
                          f"p95 {r['p95_ms']:>7} ms  p99 {r['p99_ms']:>7} ms  {r['requests_per_s']:>7} req/s  "
                          f"errors {r['errors']} {r['error_kinds'] or ''}", flush=True)

            for n in args.pollers:
                run({"poll": (n, poll, 200)})
            for n in args.submitters:
                run({"submit": (n, submit, 202)})
            run({"poll": (args.mixed_pollers, poll, 200), "submit": (args.mixed_submitters, submit, 202)})
            if args.keep:
                print(f"  kept {root}")
            return {"database": kind, "levels": levels}
        finally:
            if api is not None:
                stop_group(api, 20)
            redis.flushdb()
            dispose_all()
            if drop is not None:
                drop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--databases", default="sqlite,postgresql")
    ap.add_argument("--pollers", default="50,100,200", help="levels of concurrent pollers")
    ap.add_argument("--submitters", default="16,32,64", help="levels of concurrent submitters")
    ap.add_argument("--mixed-pollers", type=int, default=200)
    ap.add_argument("--mixed-submitters", type=int, default=64)
    ap.add_argument("--duration", type=float, default=8.0, help="seconds per level")
    ap.add_argument("--api-processes", type=int, default=2, help="uvicorn worker processes of the API")
    ap.add_argument("--keep", action="store_true", help="keep the data directory and API log (printed)")
    add_output(ap, results_dir("bench") / "load.json")
    args = ap.parse_args()
    args.pollers = [int(x) for x in args.pollers.split(",") if x]
    args.submitters = [int(x) for x in args.submitters.split(",") if x]
    results: dict[str, Any] = {
        "machine": machine(),
        "settings": {"duration_s": args.duration, "api_processes": args.api_processes, "broker": "redis"},
        "runs": [],
    }
    print(f"Load benchmark ({os.cpu_count()} CPUs; API, Redis, database and load generator on this machine)")
    for kind in args.databases.split(","):
        results["runs"].append(bench_database(kind, args))
    write_json(args.output, results)


if __name__ == "__main__":
    main()
