"""The service end to end: real Redis, real worker processes, the API under uvicorn, real files.

Upload a shared character and clip, run jobs and watch their progress, download and validate results, a 2 x 2
batch, cancel, a signed webhook to a local server, key isolation, bad uploads, and a worker killed with -9 whose
job is picked up again by the reaper.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_harness import Service

from api.security import SIGNATURE_HEADER, verify_signature

pytestmark = pytest.mark.service

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from gltf_validator import assert_valid_glb  # noqa: E402

sys.path.remove(str(HERE.parent))

FINISHED = ("succeeded", "failed", "canceled")
# A job that runs a while: 1,200 frames of the long clip (60 fps) at 30 fps is 600 output frames on a 13,380-vertex
# body, under the default frame x vertex cap (RETARGET_API_MAX_JOB_FRAME_VERTICES, 40 million).
LONG_OPTIONS = {"fps": 30, "frame_end": 1200}


class Client:
    """A few calls on top of httpx with one key."""

    def __init__(self, svc: Service, headers: dict[str, str]) -> None:
        self.http = httpx.Client(base_url=svc.base_url, headers=headers, timeout=120)

    def upload(self, kind: str, path: Path, raw: bool = False) -> httpx.Response:
        if raw:
            def chunks() -> Iterator[bytes]:  # no Content-Length: chunked transfer
                with open(path, "rb") as fh:
                    yield from iter(lambda: fh.read(256 * 1024), b"")
            return self.http.post(f"/v1/{kind}", params={"filename": path.name}, content=chunks())
        with open(path, "rb") as fh:
            return self.http.post(f"/v1/{kind}", files={"file": (path.name, fh)})

    def job(self, motion: str, target: str, **extra: Any) -> dict[str, Any]:
        r = self.http.post("/v1/jobs", json={"motion_id": motion, "target_character_id": target, **extra})
        assert r.status_code == 202, r.text
        return r.json()  # type: ignore[no-any-return]

    def wait(self, job_id: str, timeout: float = 120.0, until: tuple[str, ...] = FINISHED) -> list[dict[str, Any]]:
        """Poll until the job is in one of ``until``; returns every distinct state seen."""
        seen: list[dict[str, Any]] = []
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            j = self.http.get(f"/v1/jobs/{job_id}").json()
            if not seen or (j["status"], j["stage"], j["progress"]) != (seen[-1]["status"], seen[-1]["stage"],
                                                                        seen[-1]["progress"]):
                seen.append(j)
            if j["status"] in until:
                return seen
            time.sleep(0.05)
        raise TimeoutError(f"job {job_id} still {seen[-1]['status']} after {timeout} s")


class Hook:
    """A local webhook receiver."""

    def __init__(self) -> None:
        self.received: list[tuple[dict[str, str], bytes]] = []
        self.event = threading.Event()
        hook = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                hook.received.append((dict(self.headers.items()), body))
                self.send_response(204)
                self.end_headers()
                hook.event.set()

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hooks/retarget"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()


@pytest.fixture(scope="module")
def alice(service: Service) -> Client:
    return Client(service, service.key("alice"))


@pytest.fixture(scope="module")
def files(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Shared files, plus a long clip (a real clip played four times) for jobs that must run a while."""
    src = (shared_data / "motions" / "cmu" / "001_01.bvh").read_text()
    head, motion = src.split("MOTION", 1)
    lines = motion.strip().splitlines()
    frames = lines[2:]
    long_clip = tmp_path_factory.mktemp("clips") / "001_01_x4.bvh"
    long_clip.write_text(f"{head}MOTION\nFrames: {len(frames) * 4}\n{lines[1]}\n" + "\n".join(frames * 4) + "\n")
    return {
        "character": shared_data / "characters" / "mh_male_skinny.glb",
        "character2": shared_data / "characters" / "mh_female_average.glb",
        "clip": shared_data / "motions" / "cmu" / "007_03.bvh",
        "clip2": shared_data / "motions" / "cmu" / "002_03.bvh",
        "long": long_clip,
    }


@pytest.fixture(scope="module")
def uploaded(alice: Client, files: dict[str, Path]) -> dict[str, dict[str, Any]]:
    out = {}
    for name, kind, raw in (("character", "characters", False), ("clip", "motions", True),
                            ("character2", "characters", False), ("clip2", "motions", False),
                            ("long", "motions", False)):
        r = alice.upload(kind, files[name], raw=raw)
        assert r.status_code == 201, r.text
        out[name] = r.json()
    return out


def test_ready_with_workers(service: Service) -> None:
    r = httpx.get(f"{service.base_url}/readyz").json()
    assert r["checks"]["broker"]["transport"] == "redis"
    assert {"cpu", "io"} <= set(r["checks"]["workers"]["queues"])
    assert httpx.get(f"{service.base_url}/healthz").json() == {"status": "ok"}


def test_uploads_report_what_was_found(uploaded: dict[str, dict[str, Any]], files: dict[str, Path]) -> None:
    ch, clip = uploaded["character"], uploaded["clip"]
    assert ch["format"] == "glb" and len(ch["info"]["joints"]) == 22 and 1.6 < ch["info"]["height_m"] < 2.0
    assert ch["info"]["mapping"] and ch["size_bytes"] == files["character"].stat().st_size
    assert clip["format"] == "bvh" and clip["info"]["frames"] == 208 and clip["info"]["fps"] == 60
    assert clip["name"] == "007_03" and clip["filename"] == "007_03.bvh"  # raw chunked upload named by ?filename=


def test_job_progress_results_and_signed_webhook(alice: Client, uploaded: dict[str, dict[str, Any]],
                                                 tmp_path: Path) -> None:
    hook = Hook()
    try:
        job = alice.job(uploaded["clip"]["id"], uploaded["character"]["id"], options={"frame_end": 60},
                        callback_url=hook.url)
        seen = alice.wait(job["id"])
        final = seen[-1]
        assert final["status"] == "succeeded", final["message"]
        assert any(s["status"] == "running" for s in seen)
        progress = [s["progress"] for s in seen if s["status"] == "running"]
        assert progress == sorted(progress) and final["progress"] == 1.0
        stages = {s["stage"] for s in seen}
        assert {"read", "write"} & stages, stages
        assert final["timings"]["run_seconds"] > 0 and "copy" in final["timings"]["stages"]

        assert set(final["results"]) == {"result_glb", "before_glb", "metrics_json", "source_glb"}
        for key, name in (("result_glb", "result.glb"), ("before_glb", "before.glb"), ("source_glb", "source.glb")):
            r = alice.http.get(final["results"][key])
            assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
            assert f'filename="{job["id"]}-{name}"' in r.headers["content-disposition"]
            (tmp_path / name).write_bytes(r.content)
            assert_valid_glb(tmp_path / name)
        r = alice.http.get(final["results"]["metrics_json"])
        assert r.headers["content-type"] == "application/json"
        metrics = r.json()
        assert isinstance(metrics, dict) and metrics

        assert hook.event.wait(30), "no webhook arrived"
        headers, body = hook.received[0]
        secret = alice.http.get("/v1/me").json()["webhook_secret"]
        assert verify_signature(secret, body, headers[SIGNATURE_HEADER])
        payload = json.loads(body)
        assert payload["event"] == "job.succeeded" and payload["job"]["id"] == job["id"]
        assert payload["job"]["results"]["result_glb"].endswith("/result.glb")
        delivered = alice.http.get(f"/v1/jobs/{job['id']}").json()["webhook"]
        deadline = time.monotonic() + 10
        while delivered["status"] != "delivered" and time.monotonic() < deadline:
            time.sleep(0.2)
            delivered = alice.http.get(f"/v1/jobs/{job['id']}").json()["webhook"]
        assert delivered["status"] == "delivered" and delivered["last_status_code"] == 204
    finally:
        hook.server.shutdown()


def test_batch_two_by_two(alice: Client, uploaded: dict[str, dict[str, Any]]) -> None:
    r = alice.http.post("/v1/batches", json={
        "name": "2x2", "motion_ids": [uploaded["clip"]["id"], uploaded["clip2"]["id"]],
        "target_character_ids": [uploaded["character"]["id"], "builtin:male_bulky"],
        "options": {"frame_end": 30}})
    assert r.status_code == 202, r.text
    batch = r.json()
    assert batch["total"] == 4
    for j in batch["jobs"]:
        assert alice.wait(j["id"])[-1]["status"] == "succeeded"
    b = alice.http.get(f"/v1/batches/{batch['id']}").json()
    assert b["status"] == "succeeded" and b["counts"]["succeeded"] == 4 and b["progress"] == 1.0
    builtin_job = next(j for j in b["jobs"] if j["target_character_id"] == "builtin:male_bulky")
    assert alice.http.get(builtin_job["results"]["result_glb"]).status_code == 200


def test_cancel_queued_and_running(alice: Client, uploaded: dict[str, dict[str, Any]]) -> None:
    running = alice.job(uploaded["long"]["id"], uploaded["character"]["id"], options=LONG_OPTIONS)
    queued = alice.job(uploaded["clip"]["id"], uploaded["character"]["id"], options={"frame_end": 30})
    r = alice.http.post(f"/v1/jobs/{queued['id']}/cancel")
    assert r.status_code == 200 and r.json()["status"] == "canceled"
    alice.wait(running["id"], until=("running",))
    r = alice.http.post(f"/v1/jobs/{running['id']}/cancel")
    assert r.status_code == 200 and r.json()["cancel_requested"] is True
    final = alice.wait(running["id"])[-1]
    assert final["status"] == "canceled" and final["results"] is None, final
    assert alice.http.get(f"/v1/jobs/{running['id']}/result.glb").status_code == 409
    time.sleep(1.0)  # the canceled queued job's message reaches the worker and is skipped
    assert alice.http.get(f"/v1/jobs/{queued['id']}").json()["status"] == "canceled"
    retried = alice.http.post(f"/v1/jobs/{queued['id']}/retry").json()
    assert retried["attempt"] == 2
    assert alice.wait(queued["id"])[-1]["status"] == "succeeded"


def test_builtin_and_generated_bodies(alice: Client, uploaded: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    r = alice.http.post("/v1/characters/builtin", json={"name": "tall heavy",
                                                        "params": {"height": 1.92, "weight": 0.9, "gender": 1.0}})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["origin"] == "generated" and abs(body["info"]["height_m"] - 1.92) < 0.02
    (tmp_path / "body.glb").write_bytes(alice.http.get(body["links"]["file"]).content)
    assert_valid_glb(tmp_path / "body.glb")
    r = alice.http.post("/v1/characters/builtin", json={"params": {"height": 7}})
    assert r.status_code == 422 and "height" in r.json()["detail"]
    job = alice.job(uploaded["clip2"]["id"], body["id"], options={"frame_end": 20})
    assert alice.wait(job["id"])[-1]["status"] == "succeeded"
    # built-in presets are listed for everyone and get a downloadable GLB once the io worker has made them
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        builtins = [c for c in alice.http.get("/v1/characters", params={"limit": 100}).json()["items"]
                    if c["builtin"]]
        if builtins and all(c["sha256"] for c in builtins):
            break
        time.sleep(1)
    assert {"builtin:male_average", "builtin:female_average"} <= {c["id"] for c in builtins}
    male = next(c for c in builtins if c["id"] == "builtin:male_average")
    assert len(male["info"]["joints"]) == 22
    assert alice.http.get(male["links"]["file"]).content[:4] == b"glTF"


def test_key_isolation(service: Service, alice: Client, uploaded: dict[str, dict[str, Any]]) -> None:
    bob = Client(service, service.key("bob"))
    job = alice.job(uploaded["clip"]["id"], uploaded["character"]["id"], options={"frame_end": 10})
    for path in (f"/v1/jobs/{job['id']}", f"/v1/motions/{uploaded['clip']['id']}",
                 f"/v1/characters/{uploaded['character']['id']}", f"/v1/jobs/{job['id']}/metrics.json"):
        assert bob.http.get(path).status_code == 404, path
    assert bob.http.get("/v1/jobs").json()["total"] == 0
    chars = bob.http.get("/v1/characters", params={"limit": 100}).json()["items"]
    assert chars and all(c["builtin"] for c in chars)  # only the shared built-in bodies
    r = bob.http.post("/v1/jobs", json={"motion_id": uploaded["clip"]["id"], "target_character_id": "builtin:child"})
    assert r.status_code == 422
    assert httpx.get(f"{service.base_url}/v1/jobs").status_code == 401
    alice.wait(job["id"])


def test_bad_uploads_are_rejected_with_the_problem(alice: Client, files: dict[str, Path], tmp_path: Path) -> None:
    png = tmp_path / "photo.glb"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 1000)
    r = alice.upload("characters", png)
    assert r.status_code == 415 and "not a recognised file type" in r.json()["detail"]

    data = files["character"].read_bytes()
    cut = tmp_path / "cut.glb"
    cut.write_bytes(data[: len(data) // 3])
    r = alice.upload("characters", cut)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail.startswith("cut.glb: ") and any(w in detail for w in ("truncat", "short", "end of", "length"))

    text = files["clip2"].read_text().splitlines()
    start = next(i for i, line in enumerate(text) if line.startswith("Frame Time")) + 1
    values = text[start + 5].split()
    values[4] = "nan"
    text[start + 5] = " ".join(values)
    nan = tmp_path / "nan.bvh"
    nan.write_text("\n".join(text) + "\n")
    r = alice.upload("motions", nan)
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith("nan.bvh: ") and "nan" in r.json()["detail"].lower()

    def too_big() -> Iterator[bytes]:
        yield b"HIERARCHY\n"
        for _ in range(40):
            yield b"#" * (1024 * 1024)

    r = alice.http.post("/v1/motions", content=too_big())
    assert r.status_code == 413 and "larger than the limit" in r.json()["detail"]
    assert alice.http.get("/v1/motions", params={"limit": 100}).json()["total"] == 3  # nothing registered


def test_reaper_requeues_the_job_of_a_killed_worker(service: Service, alice: Client,
                                                    uploaded: dict[str, dict[str, Any]]) -> None:
    job = alice.job(uploaded["long"]["id"], uploaded["character"]["id"], options=LONG_OPTIONS)
    seen = alice.wait(job["id"], until=("running",))
    first_worker = seen[-1]["worker"]
    service.kill("cpu")  # kill -9 the worker and its pool process mid-job
    service.start_worker("cpu", "cpu")
    states = alice.wait(job["id"], timeout=240)
    final = states[-1]
    assert final["status"] == "succeeded", (final, service.log_tail())
    assert final["attempt"] == 2 and final["worker"] != first_worker, (states, service.log_tail())
    assert alice.http.get(final["results"]["result_glb"]).status_code == 200
