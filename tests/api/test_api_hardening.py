"""Hardening of the HTTP API: idempotency keys, list bounds, JSON 404/405 under /v1, the OpenAPI document's 401
and 422, security headers, review links, quotas, job size, callback URLs, multipart limits, queue notes."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from api_testkit import ApiEnv
from sqlalchemy import func, select

from api.db import get_engine, session_scope
from api.models import ApiKey, Asset, Job
from api.services import submission

GLB = b"glTF\x02\x00\x00\x00" + b"\x00" * 200
BVH = b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\n"


def assets(env: ApiEnv, h: dict[str, str], frames: int = 100, fps: float = 30.0, vertices: int = 1000
           ) -> tuple[str, str]:
    m = env.client.post("/v1/motions", files={"file": ("walk.bvh", BVH)}, headers=h).json()["id"]
    c = env.client.post("/v1/characters", files={"file": ("body.glb", GLB)}, headers=h).json()["id"]
    with session_scope(env.url) as s:
        s.get(Asset, m).info = {"frames": frames, "fps": fps, "duration_s": frames / fps}
        s.get(Asset, c).info = {"vertices": vertices}
    return m, c


def jobs_of(env: ApiEnv) -> int:
    with session_scope(env.url) as s:
        return s.scalar(select(func.count()).select_from(Job)) or 0


def test_idempotency_key_makes_one_job(api_env: ApiEnv) -> None:
    h = api_env.key()
    m, c = assets(api_env, h)
    body: dict[str, Any] = {"motion_id": m, "target_character_id": c}
    r1 = api_env.client.post("/v1/jobs", json=body, headers={**h, "Idempotency-Key": "k-1"})
    r2 = api_env.client.post("/v1/jobs", json=body, headers={**h, "Idempotency-Key": "k-1"})
    assert r1.status_code == r2.status_code == 202 and r1.json()["id"] == r2.json()["id"]
    assert r2.headers["idempotent-replayed"] == "true" and jobs_of(api_env) == 1
    r3 = api_env.client.post("/v1/jobs", json={**body, "options": {"frame_end": 5}},
                             headers={**h, "Idempotency-Key": "k-1"})
    assert r3.status_code == 422 and "Idempotency-Key" in r3.json()["detail"]
    b1 = api_env.client.post("/v1/batches", json={"motion_ids": [m], "target_character_ids": [c]},
                             headers={**h, "Idempotency-Key": "b-1"})
    b2 = api_env.client.post("/v1/batches", json={"motion_ids": [m], "target_character_ids": [c]},
                             headers={**h, "Idempotency-Key": "b-1"})
    assert b1.json()["id"] == b2.json()["id"] and jobs_of(api_env) == 2


def test_idempotency_key_on_uploads_and_generated_bodies(api_env: ApiEnv) -> None:
    from api.queue import TASK_MAKE_BODY
    from worker.assets import answer

    h = api_env.key()
    r1 = api_env.client.post("/v1/motions", files={"file": ("walk.bvh", BVH)}, headers={**h, "Idempotency-Key": "u-1"})
    r2 = api_env.client.post("/v1/motions", files={"file": ("walk.bvh", BVH)}, headers={**h, "Idempotency-Key": "u-1"})
    assert r1.status_code == r2.status_code == 201 and r1.json()["id"] == r2.json()["id"]
    assert r2.headers["idempotent-replayed"] == "true" and len(api_env.celery.named("retarget.inspect")) == 1
    r3 = api_env.client.post("/v1/motions", files={"file": ("run.bvh", BVH + b"\n")},
                             headers={**h, "Idempotency-Key": "u-1"})
    assert r3.status_code == 422 and "Idempotency-Key" in r3.json()["detail"]

    def make_body(kwargs: dict[str, Any]) -> None:
        answer(api_env.settings, kwargs["call_id"], {"sha256": "c" * 64, "size_bytes": 10, "name": "made",
                                                      "info": {"vertices": 10}, "params": kwargs["params"]})

    api_env.celery.handlers[TASK_MAKE_BODY] = make_body
    body = {"params": {"height": 1.8}}
    b1 = api_env.client.post("/v1/characters/builtin", json=body, headers={**h, "Idempotency-Key": "g-1"})
    b2 = api_env.client.post("/v1/characters/builtin", json=body, headers={**h, "Idempotency-Key": "g-1"})
    assert b1.status_code == b2.status_code == 201, b1.text
    assert b1.json()["id"] == b2.json()["id"] and b2.headers["idempotent-replayed"] == "true"
    assert len(api_env.celery.named(TASK_MAKE_BODY)) == 1


def test_jobs_are_sent_and_marked_sent(api_env: ApiEnv) -> None:
    h = api_env.key()
    m, c = assets(api_env, h)
    job = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c}, headers=h).json()
    api_env.client.app.state.sent_marker.flush()  # recorded in batches by the API process's marker thread
    with session_scope(api_env.url) as s:
        assert s.get(Job, job["id"]).sent_at is not None
    api_env.celery.fail = True
    job = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c}, headers=h).json()
    with session_scope(api_env.url) as s:
        assert s.get(Job, job["id"]).sent_at is None  # the reaper sends it within seconds


def test_submission_waited_on_by_a_lock_is_written_in_a_thread(api_env: ApiEnv,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """A submission's write is made on the event loop; when another writer holds the lock it needs (SQLite's
    write lock, a PostgreSQL row lock) past ``loop_write_wait_seconds``, it is made in a thread instead, once."""
    in_thread: list[str | None] = []

    def spy(url: str, key: Any, values: dict[str, Any], idem: str | None, *rest: Any) -> Any:
        in_thread.append(idem)
        return write_in_thread(url, key, values, idem, *rest)

    write_in_thread = submission._write_job_in_thread
    monkeypatch.setattr(submission, "_write_job_in_thread", spy)
    h = api_env.key()
    m, c = assets(api_env, h)
    body = {"motion_id": m, "target_character_id": c}
    hold = get_engine(api_env.url).connect()
    if api_env.url.startswith("sqlite"):
        hold.exec_driver_sql("BEGIN IMMEDIATE")  # the write lock
    else:
        hold.begin()
        owner = select(Asset.owner_id).where(Asset.id == m).scalar_subquery()
        hold.execute(select(ApiKey).where(ApiKey.id == owner).with_for_update())  # blocks the job's foreign key
    releaser = threading.Timer(0.5, hold.rollback)
    releaser.start()
    try:
        r = api_env.client.post("/v1/jobs", json=body, headers=h)  # waits in a thread until the lock is free
        assert r.status_code == 202, r.text
        r = api_env.client.post("/v1/jobs", json=body, headers={**h, "Idempotency-Key": "lock-1"})
        assert r.status_code == 202, r.text
    finally:
        releaser.join()
        hold.close()
    assert in_thread == [None] and jobs_of(api_env) == 2  # the second found the lock free again
    r = api_env.client.post("/v1/jobs", json=body, headers={**h, "Idempotency-Key": "lock-1"})
    assert r.headers["idempotent-replayed"] == "true" and jobs_of(api_env) == 2


def test_list_bounds_and_unknown_paths(api_env: ApiEnv) -> None:
    h = api_env.key()
    for path in ("/v1/jobs", "/v1/batches", "/v1/motions", "/v1/characters"):
        r = api_env.client.get(path, params={"offset": "9223372036854775808"}, headers=h)
        assert r.status_code == 422 and r.json()["detail"].startswith("invalid request"), r.text
    r = api_env.client.get("/v1/nothing/here", headers=h)
    assert r.status_code == 404 and r.headers["content-type"] == "application/json"
    r = api_env.client.put("/v1/jobs", headers=h)
    assert r.status_code == 405 and "GET" in r.headers["allow"] and "detail" in r.json()


def test_openapi_documents_401_and_422_as_errors(api_env: ApiEnv) -> None:
    doc = api_env.client.get("/openapi.json").json()
    ops = [(p, m, op) for p, item in doc["paths"].items() for m, op in item.items()]
    keyed = [(p, m, op) for p, m, op in ops if op.get("security")]
    assert keyed and all("401" in op["responses"] for _, _, op in keyed)
    for _, _, op in ops:
        if "422" in op["responses"]:
            assert op["responses"]["422"]["content"]["application/json"]["schema"] == {
                "$ref": "#/components/schemas/ErrorOut"}
    r = api_env.client.post("/v1/jobs", json={"motion_id": 1}, headers=api_env.key())
    assert r.status_code == 422 and isinstance(r.json()["detail"], str) and r.json()["errors"]


def test_security_headers_and_readyz_without_a_key(api_env: ApiEnv) -> None:
    r = api_env.client.get("/healthz")
    assert r.headers["x-content-type-options"] == "nosniff" and r.headers["x-frame-options"] == "DENY"
    body = api_env.client.get("/readyz").json()
    assert "live" not in body["checks"]["workers"]


def test_review_links_open_one_job_read_only_until_revoked(api_env: ApiEnv) -> None:
    h = api_env.key()
    m, c = assets(api_env, h)
    job = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c}, headers=h).json()
    link = api_env.client.post(f"/v1/jobs/{job['id']}/review-links", json={"label": "director"}, headers=h)
    assert link.status_code == 201, link.text
    token = link.json()["token"]
    r = api_env.client.get(f"/v1/review/{token}")
    assert r.status_code == 200 and r.json()["job_id"] == job["id"]
    forged = token[:-1] + ("1" if token[-1] == "0" else "0")  # another last digit (the same one 1 time in 16)
    assert api_env.client.get(f"/v1/review/{forged}").status_code == 404  # a forged signature
    assert api_env.client.get("/v1/jobs", headers={"X-API-Key": token}).status_code == 401  # not a key
    other = api_env.key("other")
    assert api_env.client.post(f"/v1/jobs/{job['id']}/review-links", json={}, headers=other).status_code == 404
    d = api_env.client.delete(f"/v1/jobs/{job['id']}/review-links/{link.json()['id']}", headers=h)
    assert d.status_code == 204 and api_env.client.get(f"/v1/review/{token}").status_code == 404


def test_job_size_cap_and_quota(api_env: ApiEnv) -> None:
    h = api_env.key()
    m, c = assets(api_env, h, frames=10, fps=1.0, vertices=20_000)
    r = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c, "options": {"fps": 240}},
                            headers=h)
    assert r.status_code == 422 and "2161 frames" in r.json()["detail"] and "MAX_JOB_FRAME_VERTICES" in r.text
    api_env.settings.max_active_jobs_per_key = 1
    assert api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c}, headers=h
                               ).status_code == 202
    r = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c}, headers=h)
    assert r.status_code == 429 and "quota" in r.json()["detail"]


def test_callback_urls_to_internal_addresses_are_refused(api_env: ApiEnv) -> None:
    h = api_env.key()
    m, c = assets(api_env, h)
    api_env.settings.callback_allowed_hosts = []
    for url in ("http://169.254.169.254/", "http://2130706433/", "http://user:pw@example.com/", "http://[::1]/"):
        r = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c, "callback_url": url},
                                headers=h)
        assert r.status_code == 422, (url, r.text)


def test_multipart_bypasses_are_refused(api_env: ApiEnv) -> None:
    h = api_env.key()
    cap = api_env.settings.max_upload_bytes
    boundary = "b" * 300
    body = f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.bvh\"\r\n\r\n".encode()
    r = api_env.client.post("/v1/motions", content=body + BVH + f"\r\n--{boundary}--\r\n".encode(),
                            headers={**h, "Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert r.status_code == 400 and "boundary" in r.json()["detail"]

    def chunks() -> Any:  # chunked: no Content-Length; the file is small, the epilogue huge
        yield b"--x\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.bvh\"\r\n\r\n" + BVH
        yield b"\r\n--x--\r\n"
        for _ in range(cap // 65536 + 4):
            yield b"e" * 65536

    r = api_env.client.post("/v1/motions", content=chunks(),
                            headers={**h, "Content-Type": "multipart/form-data; boundary=x"})
    assert r.status_code == 413


def test_queued_job_on_a_queue_no_worker_serves_says_so(api_env: ApiEnv) -> None:
    h = api_env.key()
    m, c = assets(api_env, h)
    job = api_env.client.post("/v1/jobs", json={"motion_id": m, "target_character_id": c, "queue": "gpu"},
                              headers=h).json()
    assert job["note"] and "'gpu'" in job["note"]


def test_nul_characters_are_a_422_not_a_server_error(api_env: ApiEnv) -> None:
    h = api_env.key()
    r = api_env.client.post("/v1/jobs", json={"motion_id": "mot\x00", "target_character_id": "chr_x"}, headers=h)
    assert r.status_code == 422 and "motion_id" in r.json()["detail"], r.text
    r = api_env.client.get("/v1/jobs/job%00x", headers=h)
    assert r.status_code in (404, 422), r.text  # PostgreSQL refuses NUL in text: a 422, never a 500
    r = api_env.client.post("/v1/batches", json={"name": "a\x00b", "motion_ids": ["m"], "target_character_ids": ["c"]},
                            headers=h)
    assert r.status_code == 422, r.text


def test_405_names_only_the_methods_of_the_path_with_the_front_end_mounted(tmp_path: Any,
                                                                          database_url: str) -> None:
    """The front end's mount at / matches every method; the Allow header must still list only the path's own."""
    from fastapi.testclient import TestClient

    from api.main import create_app
    from api.settings import Settings

    front = tmp_path / "front"
    front.mkdir()
    (front / "index.html").write_text("<!doctype html><title>app</title>")
    app = create_app(Settings(data_dir=tmp_path / "data", database_url=database_url, frontend_dir=front))
    with TestClient(app) as client:
        r = client.delete("/v1/info")
        assert r.status_code == 405 and r.headers["allow"] == "GET", r.headers
        r = client.put("/v1/jobs/job_x")
        assert r.status_code == 405 and r.headers["allow"] == "GET", r.headers
        assert client.get("/some/page").status_code == 200  # the front end still answers its own paths
