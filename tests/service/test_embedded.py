"""The embedded default (``python -m api.serve``): API and workers on one machine, no Redis, SQLite broker."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from service_harness import REPO, free_port

pytestmark = pytest.mark.service


def test_embedded_serve_runs_a_job_without_redis(tmp_path: Path, shared_data: Path) -> None:
    port = free_port()
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("RETARGET_API_") and k not in ("DATABASE_URL", "REDIS_URL")}
    env.update({"RETARGET_API_DATA_DIR": str(tmp_path / "data"), "RETARGET_API_DEV_API_KEY": "test-dev-key",
                "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"})
    log = open(tmp_path / "serve.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen([sys.executable, "-m", "api.serve", "--port", str(port)], cwd=REPO, env=env,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        ready = None
        while time.monotonic() < deadline:
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()[-3000:]
            try:
                r = httpx.get(f"{base}/readyz", timeout=5)
                if r.status_code == 200:
                    ready = r.json()
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        assert ready is not None, (tmp_path / "serve.log").read_text()[-3000:]
        assert ready["checks"]["broker"]["transport"] == "sqlite (embedded)"
        assert "test-dev-key" in (tmp_path / "serve.log").read_text()

        http = httpx.Client(base_url=base, headers={"X-API-Key": "test-dev-key"}, timeout=120)
        with open(shared_data / "motions" / "cmu" / "002_03.bvh", "rb") as fh:
            motion = http.post("/v1/motions", files={"file": ("002_03.bvh", fh)})
        assert motion.status_code == 201, motion.text
        job = http.post("/v1/jobs", json={"motion_id": motion.json()["id"],
                                          "target_character_id": "builtin:female_average",
                                          "options": {"frame_end": 30}})
        assert job.status_code == 202, job.text
        job_id = job.json()["id"]
        status = None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            status = http.get(f"/v1/jobs/{job_id}").json()
            if status["status"] in ("succeeded", "failed", "canceled"):
                break
            time.sleep(0.2)
        assert status is not None and status["status"] == "succeeded", status
        assert http.get(status["results"]["result_glb"]).content[:4] == b"glTF"
        assert (tmp_path / "data" / "broker.sqlite").is_file()
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    leftovers = subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True).stdout.split()
    assert leftovers == [], f"worker processes left behind: {leftovers}"
