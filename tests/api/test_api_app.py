"""The HTTP API with a recording Celery stand-in (no worker process), on SQLite and on PostgreSQL."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from api_testkit import ApiEnv, answer_inspect
from sqlalchemy import func, select

from api.db import session_scope, utcnow
from api.models import Asset, Job, WebhookDelivery, WorkerProcess
from api.queue import TASK_DELIVER_WEBHOOK, TASK_INSPECT, TASK_RUN_JOB

GLB = b"glTF\x02\x00\x00\x00" + b"\x00" * 200
BVH = b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\n"


def upload(env: ApiEnv, kind: str, data: bytes, headers: dict[str, str], filename: str = "f.bin",
           **params: Any) -> Any:
    return env.client.post(f"/v1/{kind}", files={"file": (filename, data)}, headers=headers, params=params)


def blob_files(env: ApiEnv) -> list[Path]:
    return [p for p in (env.settings.data_dir / "blobs").rglob("*") if p.is_file()]


def make_assets(env: ApiEnv, h: dict[str, str]) -> tuple[str, str]:
    m = upload(env, "motions", BVH + b"#m", h, "walk.bvh")
    c = upload(env, "characters", GLB + b"c", h, "body.glb")
    assert m.status_code == 201 and c.status_code == 201, (m.text, c.text)
    return m.json()["id"], c.json()["id"]


# Keys -------------------------------------------------------------------------------------------------------
def test_requests_without_a_valid_key_are_refused(api_env: ApiEnv) -> None:
    r = api_env.client.get("/v1/jobs")
    assert r.status_code == 401 and "X-API-Key" in r.json()["detail"]
    r = api_env.client.get("/v1/jobs", headers={"X-API-Key": "rk_nope"})
    assert r.status_code == 401 and "unknown" in r.json()["detail"]


def test_health_needs_no_key(api_env: ApiEnv) -> None:
    assert api_env.client.get("/healthz").json() == {"status": "ok"}


# Uploads ----------------------------------------------------------------------------------------------------
def test_upload_multipart_reports_what_was_found_and_stores_once(api_env: ApiEnv) -> None:
    h = api_env.key()
    r = upload(api_env, "characters", GLB, h, "hero.glb")
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["format"] == "glb" and body["name"] == "hero" and body["filename"] == "hero.glb"
    assert body["info"]["joints"] == ["Hips"] and body["builtin"] is False
    assert r.headers["location"] == f"/v1/characters/{body['id']}"
    assert len(api_env.celery.named(TASK_INSPECT)) == 1
    # the same bytes again by the same key (raw body): one blob, no second parse
    r1 = api_env.client.post("/v1/characters?filename=again.glb", content=GLB,
                             headers={**h, "Content-Type": "application/octet-stream"})
    assert r1.status_code == 201 and len(api_env.celery.named(TASK_INSPECT)) == 1
    # by another key: still one blob, but parsed again for that key (no file name from the other key, and no
    # faster answer telling it someone has the file)
    h2 = api_env.key("other")
    r2 = api_env.client.post("/v1/characters?filename=copy.glb&name=Copy", content=GLB,
                             headers={**h2, "Content-Type": "application/octet-stream"})
    assert r2.status_code == 201, r2.text
    assert r2.json()["sha256"] == body["sha256"] and r2.json()["name"] == "Copy"
    assert r2.json()["filename"] == "copy.glb" and "hero" not in r2.text
    assert len(api_env.celery.named(TASK_INSPECT)) == 2
    assert len(blob_files(api_env)) == 1


def test_chunked_raw_upload(api_env: ApiEnv) -> None:
    h = api_env.key()

    def chunks():  # no Content-Length: Transfer-Encoding chunked
        yield BVH
        yield b"#" * 5000

    r = api_env.client.post("/v1/motions?filename=c.bvh", content=chunks(), headers=h)
    assert r.status_code == 201, r.text
    assert r.json()["size_bytes"] == len(BVH) + 5000 and r.json()["format"] == "bvh"


def test_upload_over_the_cap_is_413_declared_or_chunked(api_env: ApiEnv) -> None:
    h = api_env.key()
    big = GLB + b"\x00" * (api_env.settings.max_upload_bytes + 1)
    r = upload(api_env, "characters", big, h, "big.glb")
    assert r.status_code == 413 and "larger than the limit" in r.json()["detail"]

    def chunks():
        yield GLB
        for _ in range(40):
            yield b"\x00" * 65536

    r = api_env.client.post("/v1/characters", content=chunks(), headers=h)
    assert r.status_code == 413, r.text
    assert not blob_files(api_env) and not list((api_env.settings.data_dir / "tmp").glob("*.part"))
    assert not api_env.celery.named(TASK_INSPECT)


def test_wrong_type_is_415_naming_the_problem(api_env: ApiEnv) -> None:
    h = api_env.key()
    r = upload(api_env, "characters", b"\x89PNG\r\n\x1a\n" + b"\x00" * 100, h, "photo.glb")
    assert r.status_code == 415 and "not a recognised file type" in r.json()["detail"]
    assert "photo.glb" in r.json()["detail"]
    r = upload(api_env, "characters", BVH, h, "clip.bvh")
    assert r.status_code == 415 and "BVH file cannot be a character" in r.json()["detail"]
    r = api_env.client.post("/v1/motions", files={"other": ("x", b"abc")}, headers=h)
    assert r.status_code == 400 and "part named 'file'" in r.json()["detail"]
    r = api_env.client.post("/v1/motions", content=b"", headers=h)
    assert r.status_code == 400 and "empty" in r.json()["detail"]


def test_parser_rejection_is_422_and_the_blob_is_not_kept(api_env: ApiEnv) -> None:
    h = api_env.key()
    api_env.celery.handlers[TASK_INSPECT] = answer_inspect(
        api_env.settings, error_for=lambda kw: f"{kw['label']}: truncated GLB (chunk runs past the end)")
    r = upload(api_env, "characters", GLB, h, "broken.glb")
    assert r.status_code == 422
    assert r.json()["detail"] == "broken.glb: truncated GLB (chunk runs past the end)"
    assert not blob_files(api_env)
    with session_scope(api_env.url) as s:
        assert s.scalar(select(func.count()).select_from(Asset)) == 0


def test_no_worker_is_503(api_env: ApiEnv) -> None:
    h = api_env.key()
    api_env.celery.handlers.clear()
    api_env.settings.inspect_timeout_seconds = 0.5
    t = time.monotonic()
    r = upload(api_env, "motions", BVH, h, "a.bvh")
    assert r.status_code == 503 and "no worker answered" in r.json()["detail"]
    assert time.monotonic() - t < 5
    api_env.celery.fail = True
    r = upload(api_env, "motions", BVH + b"x", h, "a.bvh")
    assert r.status_code == 503 and "cannot be reached" in r.json()["detail"]


def test_list_get_download_delete_and_pagination(api_env: ApiEnv) -> None:
    h = api_env.key()
    ids = [upload(api_env, "motions", BVH + bytes([i]), h, f"m{i}.bvh").json()["id"] for i in range(3)]
    page1 = api_env.client.get("/v1/motions", headers=h).json()
    assert page1["total"] == 3 and len(page1["items"]) == 2 and page1["next_offset"] == 2
    page2 = api_env.client.get("/v1/motions", headers=h, params={"offset": 2}).json()
    assert page2["next_offset"] is None
    listed = [i["id"] for i in page1["items"] + page2["items"]]
    assert sorted(listed) == sorted(ids) and listed[0] == ids[-1]  # newest first
    r = api_env.client.get(f"/v1/motions/{ids[0]}/file", headers=h)
    assert r.status_code == 200 and r.content == BVH + bytes([0])
    assert 'filename="m0.bvh"' in r.headers["content-disposition"]
    assert api_env.client.delete(f"/v1/motions/{ids[0]}", headers=h).status_code == 204
    assert api_env.client.get(f"/v1/motions/{ids[0]}", headers=h).status_code == 404
    assert len(blob_files(api_env)) == 2


def test_builtin_characters_are_listed_for_every_key(api_env: ApiEnv) -> None:
    with session_scope(api_env.url) as s:
        s.add(Asset(id="builtin:male_average", kind="character", origin="builtin", name="male_average",
                    params={"preset": "male_average"}, info={"preset": "male_average"}))
    h = api_env.key()
    upload(api_env, "characters", GLB, h, "mine.glb")
    items = api_env.client.get("/v1/characters", headers=h, params={"limit": 10}).json()["items"]
    assert items[0]["id"] == "builtin:male_average" and items[0]["builtin"] is True and len(items) == 2
    assert api_env.client.get("/v1/characters/builtin:male_average", headers=api_env.key("b")).status_code == 200
    assert api_env.client.delete("/v1/characters/builtin:male_average", headers=h).status_code == 409
    only_mine = api_env.client.get("/v1/characters", headers=h, params={"include_builtin": False}).json()
    assert only_mine["total"] == 1


# Key isolation ----------------------------------------------------------------------------------------------
def test_one_key_never_sees_another_keys_resources(api_env: ApiEnv) -> None:
    a, b = api_env.key("a"), api_env.key("b")
    motion, character = make_assets(api_env, a)
    job = api_env.client.post("/v1/jobs", json={"motion_id": motion, "target_character_id": character},
                              headers=a).json()
    for path in (f"/v1/motions/{motion}", f"/v1/characters/{character}", f"/v1/jobs/{job['id']}",
                 f"/v1/motions/{motion}/file", f"/v1/jobs/{job['id']}/result.glb"):
        assert api_env.client.get(path, headers=b).status_code == 404, path
    assert api_env.client.post(f"/v1/jobs/{job['id']}/cancel", headers=b).status_code == 404
    assert api_env.client.delete(f"/v1/motions/{motion}", headers=b).status_code == 404
    assert api_env.client.get("/v1/jobs", headers=b).json()["total"] == 0
    assert api_env.client.get("/v1/motions", headers=b).json()["total"] == 0
    r = api_env.client.post("/v1/jobs", json={"motion_id": motion, "target_character_id": character}, headers=b)
    assert r.status_code == 422 and "motion_id" in r.json()["detail"]
    batch = api_env.client.post("/v1/batches", json={"motion_ids": [motion], "target_character_ids": [character]},
                                headers=a).json()
    assert api_env.client.get(f"/v1/batches/{batch['id']}", headers=b).status_code == 404
    assert api_env.client.post(f"/v1/batches/{batch['id']}/cancel", headers=b).status_code == 404
    assert api_env.client.get("/v1/batches", headers=b).json()["total"] == 0
    assert api_env.client.get("/v1/jobs", headers=b, params={"batch_id": batch["id"]}).json()["total"] == 0


# Jobs -------------------------------------------------------------------------------------------------------
def test_job_lifecycle_submit_cancel_retry(api_env: ApiEnv) -> None:
    h = api_env.key()
    motion, character = make_assets(api_env, h)
    r = api_env.client.post("/v1/jobs", headers=h, json={
        "motion_id": motion, "target_character_id": character, "options": {"frame_end": 30},
        "callback_url": "http://127.0.0.1:9/hook"})
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}" and job["status"] == "queued"
    assert job["options"]["frame_end"] == 30 and job["links"]["cancel"].endswith("/cancel")
    api_env.client.app.state.sent_marker.flush()  # sent by the API process's marker thread
    sent = api_env.celery.named(TASK_RUN_JOB)
    assert len(sent) == 1 and sent[0].queue == "cpu" and sent[0].kwargs == {"job_id": job["id"], "attempt": 1}
    assert api_env.client.get(f"/v1/jobs/{job['id']}/result.glb", headers=h).status_code == 409

    r = api_env.client.post(f"/v1/jobs/{job['id']}/cancel", headers=h)
    assert r.status_code == 200 and r.json()["status"] == "canceled"
    assert r.json()["webhook"]["event"] == "job.canceled"
    assert api_env.celery.named(TASK_DELIVER_WEBHOOK)
    assert api_env.client.post(f"/v1/jobs/{job['id']}/cancel", headers=h).status_code == 409

    r = api_env.client.post(f"/v1/jobs/{job['id']}/retry", headers=h)
    assert r.status_code == 202 and r.json()["status"] == "queued" and r.json()["attempt"] == 2
    api_env.client.app.state.sent_marker.flush()  # retries go through the same outbox
    assert api_env.celery.named(TASK_RUN_JOB)[-1].kwargs == {"job_id": job["id"], "attempt": 2}
    assert api_env.client.post(f"/v1/jobs/{job['id']}/retry", headers=h).status_code == 409


def test_invalid_job_requests_are_422(api_env: ApiEnv) -> None:
    h = api_env.key()
    motion, character = make_assets(api_env, h)
    r = api_env.client.post("/v1/jobs", headers=h, json={"motion_id": motion, "target_character_id": motion})
    assert r.status_code == 422 and "target_character_id" in r.json()["detail"]
    r = api_env.client.post("/v1/jobs", headers=h, json={"motion_id": motion, "target_character_id": character,
                                                          "options": {"frame_start": 50, "frame_end": 10}})
    assert r.status_code == 422 and "frame_end" in json.dumps(r.json())
    r = api_env.client.post("/v1/jobs", headers=h, json={"motion_id": motion, "target_character_id": character,
                                                          "callback_url": "not a url"})
    assert r.status_code == 422


def test_running_job_cancel_is_a_request(api_env: ApiEnv) -> None:
    h = api_env.key()
    motion, character = make_assets(api_env, h)
    job_id = api_env.client.post("/v1/jobs", headers=h, json={"motion_id": motion,
                                                              "target_character_id": character}).json()["id"]
    with session_scope(api_env.url) as s:
        job = s.get(Job, job_id)
        job.status, job.started_at, job.heartbeat_at = "running", utcnow(), utcnow()
    r = api_env.client.post(f"/v1/jobs/{job_id}/cancel", headers=h).json()
    assert r["status"] == "running" and r["cancel_requested"] is True


def test_results_download_with_types_and_names(api_env: ApiEnv) -> None:
    from worker.runner import JobRun

    h = api_env.key()
    motion, character = make_assets(api_env, h)
    job_id = api_env.client.post("/v1/jobs", headers=h, json={"motion_id": motion,
                                                              "target_character_id": character}).json()["id"]

    def fake_pipeline(inputs: Any, out_dir: Path, progress: Any, should_cancel: Any) -> Any:
        from retarget_core.jobs import JobOutputs

        progress("copy", 0.5)
        for name in ("result.glb", "before.glb"):
            (out_dir / name).write_bytes(GLB + name.encode())
        (out_dir / "metrics.json").write_text('{"summary": {"penetration": 0.1}}')
        return JobOutputs(out_dir / "result.glb", out_dir / "before.glb", out_dir / "metrics.json",
                          {"penetration": float("nan"), "skate": 0.2}, {"copy": 0.01}, ["note"])

    assert JobRun(api_env.settings, job_id, 1, "test@host").run(fake_pipeline).outcome == "succeeded"
    job = api_env.client.get(f"/v1/jobs/{job_id}", headers=h).json()
    assert job["status"] == "succeeded" and job["progress"] == 1.0 and job["summary"] == {"penetration": None,
                                                                                          "skate": 0.2}
    assert set(job["results"]) == {"result_glb", "before_glb", "metrics_json"}
    assert job["timings"]["stages"] == {"copy": 0.01} and job["timings"]["run_seconds"] is not None
    r = api_env.client.get(job["results"]["result_glb"], headers=h)
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    assert r.content == GLB + b"result.glb"
    assert f'filename="{job_id}-result.glb"' in r.headers["content-disposition"]
    r = api_env.client.get(job["results"]["metrics_json"], headers=h)
    assert r.headers["content-type"] == "application/json" and r.json()["summary"]["penetration"] == 0.1
    assert api_env.client.get(f"/v1/jobs/{job_id}/source.glb", headers=h).status_code == 404
    assert api_env.client.get("/v1/jobs", headers=h, params={"status": "succeeded"}).json()["total"] == 1
    assert api_env.client.get("/v1/jobs", headers=h, params={"status": "queued"}).json()["total"] == 0


# Batches ----------------------------------------------------------------------------------------------------
def test_batch_two_by_two_and_aggregate(api_env: ApiEnv) -> None:
    h = api_env.key()
    m1, c1 = make_assets(api_env, h)
    m2 = upload(api_env, "motions", BVH + b"#2", h, "b.bvh").json()["id"]
    c2 = upload(api_env, "characters", GLB + b"2", h, "d.glb").json()["id"]
    r = api_env.client.post("/v1/batches", headers=h, json={
        "name": "two by two", "motion_ids": [m1, m2], "target_character_ids": [c1, c2],
        "options": {"frame_end": 20}})
    assert r.status_code == 202, r.text
    batch = r.json()
    assert batch["total"] == 4 and batch["status"] == "queued" and batch["counts"]["queued"] == 4
    pairs = {(j["motion_id"], j["target_character_id"]) for j in batch["jobs"]}
    assert pairs == {(m1, c1), (m1, c2), (m2, c1), (m2, c2)}
    api_env.client.app.state.sent_marker.flush()  # batches go through the same outbox
    assert len(api_env.celery.named(TASK_RUN_JOB)) == 4
    listed = api_env.client.get("/v1/jobs", headers=h, params={"batch_id": batch["id"], "limit": 10}).json()
    assert listed["total"] == 4
    with session_scope(api_env.url) as s:
        job = s.get(Job, batch["jobs"][0]["id"])
        job.status = "failed"
        job.message = "boom"
    b = api_env.client.get(f"/v1/batches/{batch['id']}", headers=h).json()
    assert b["status"] == "running" and b["counts"]["failed"] == 1
    b = api_env.client.post(f"/v1/batches/{batch['id']}/cancel", headers=h).json()
    assert b["status"] == "failed" and b["counts"] == {"queued": 0, "running": 0, "succeeded": 0, "failed": 1,
                                                       "canceled": 3}
    r = api_env.client.post("/v1/batches", headers=h, json={"motion_ids": [m1, m2, m1],
                                                            "target_character_ids": [c1, c2, c1]})
    assert r.status_code == 422 and "limit is 6" in r.json()["detail"]
    r = api_env.client.post("/v1/batches", headers=h, json={"motion_ids": [m1], "target_character_ids": ["nope"]})
    assert r.status_code == 422
    with session_scope(api_env.url) as s:  # nothing half-created
        assert s.scalar(select(func.count()).select_from(Job)) == 4


def test_webhook_rows_are_written_when_a_queued_job_is_canceled(api_env: ApiEnv) -> None:
    h = api_env.key()
    motion, character = make_assets(api_env, h)
    job_id = api_env.client.post("/v1/jobs", headers=h, json={
        "motion_id": motion, "target_character_id": character, "callback_url": "http://127.0.0.1:1/x"}).json()["id"]
    api_env.client.post(f"/v1/jobs/{job_id}/cancel", headers=h)
    with session_scope(api_env.url) as s:
        d = s.scalar(select(WebhookDelivery).where(WebhookDelivery.job_id == job_id))
        assert d is not None and d.event == "job.canceled" and d.url == "http://127.0.0.1:1/x"
    assert api_env.celery.named(TASK_DELIVER_WEBHOOK)[-1].kwargs == {"delivery_id": d.id, "attempt": 1}


def test_broker_down_at_submission_leaves_the_job_for_the_reaper(api_env: ApiEnv) -> None:
    h = api_env.key()
    motion, character = make_assets(api_env, h)
    api_env.celery.fail = True
    r = api_env.client.post("/v1/jobs", headers=h, json={"motion_id": motion, "target_character_id": character})
    assert r.status_code == 202
    with session_scope(api_env.url) as s:
        assert s.get(Job, r.json()["id"]).sent_at is None


# Health, info, OpenAPI, front end ---------------------------------------------------------------------------
def test_readyz_needs_live_workers(api_env: ApiEnv) -> None:
    r = api_env.client.get("/readyz")
    assert r.status_code == 503
    checks = r.json()["checks"]
    assert checks["database"]["ok"] and checks["broker"]["ok"] and checks["storage"]["ok"]
    assert not checks["workers"]["ok"] and checks["workers"]["error"] == "no live worker"
    with session_scope(api_env.url) as s:
        s.add(WorkerProcess(hostname="cpu@a", queues="cpu", pid=1))
        s.add(WorkerProcess(hostname="io@a", queues="io", pid=2))
    r = api_env.client.get("/readyz")
    assert r.status_code == 200 and r.json()["checks"]["workers"]["queues"] == ["cpu", "io"]


def test_info_and_me(api_env: ApiEnv) -> None:
    h = api_env.key("studio")
    info = api_env.client.get("/v1/info").json()
    assert info["max_upload_bytes"] == 2 * 1024 * 1024 and "bvh" in info["motion_formats"]
    me = api_env.client.get("/v1/me", headers=h).json()
    assert me["name"] == "studio" and len(me["webhook_secret"]) > 20


def test_openapi_documents_every_resource(api_env: ApiEnv) -> None:
    doc = api_env.client.get("/openapi.json").json()
    paths = doc["paths"]
    for p in ("/v1/characters", "/v1/characters/builtin", "/v1/characters/{asset_id}", "/v1/motions",
              "/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/cancel", "/v1/jobs/{job_id}/retry",
              "/v1/jobs/{job_id}/result.glb", "/v1/jobs/{job_id}/before.glb", "/v1/jobs/{job_id}/metrics.json",
              "/v1/batches", "/v1/batches/{batch_id}", "/healthz", "/readyz"):
        assert p in paths, p
    content = paths["/v1/characters"]["post"]["requestBody"]["content"]
    assert {"multipart/form-data", "application/octet-stream"} <= set(content)
    assert "model/gltf-binary" in paths["/v1/jobs/{job_id}/result.glb"]["get"]["responses"]["200"]["content"]
    assert "RetargetOptions" in doc["components"]["schemas"]
    assert doc["components"]["securitySchemes"]["APIKeyHeader"]["name"] == "X-API-Key"
    for op in (paths["/v1/jobs"]["post"], paths["/v1/motions"]["post"]):
        assert op.get("description") and op.get("summary")


def test_frontend_is_served_when_built(tmp_path: Path, database_url: str) -> None:
    from fastapi.testclient import TestClient

    from api.main import create_app
    from api.settings import Settings

    dist = tmp_path / "dist"
    (dist / "assets").mkdir(parents=True)
    (dist / "index.html").write_text("<html>app</html>")
    (dist / "assets" / "app.js").write_text("console.log(1)")
    app = create_app(Settings(data_dir=tmp_path / "d", database_url=database_url, frontend_dir=dist))
    with TestClient(app) as c:
        assert c.get("/").text == "<html>app</html>"
        assert c.get("/assets/app.js").text == "console.log(1)"
        assert c.get("/review/job_123").text == "<html>app</html>"  # client-side route
        assert c.get("/assets/missing.js").status_code == 404
        assert c.get("/healthz").json() == {"status": "ok"}
        assert c.get("/v1/jobs").status_code == 401
        assert "access-control-allow-origin" not in c.get("/healthz", headers={"Origin": "http://x"}).headers


def test_make_a_body_from_parameters(api_env: ApiEnv) -> None:
    from api.queue import TASK_MAKE_BODY
    from worker.assets import answer

    def handler(kwargs: dict[str, Any]) -> None:
        if kwargs["params"].get("height", 1.7) > 2.3:
            answer(api_env.settings, kwargs["call_id"], error="invalid body parameters: height: too tall")
        else:
            answer(api_env.settings, kwargs["call_id"], {"sha256": "ab" * 32, "size_bytes": 10,
                                                         "info": {"height_m": 1.8}, "params": kwargs["params"]})

    api_env.celery.handlers[TASK_MAKE_BODY] = handler
    h = api_env.key()
    r = api_env.client.post("/v1/characters/builtin", headers=h, json={"name": "tall", "params": {"height": 1.8}})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["origin"] == "generated" and body["builtin"] is False and body["params"] == {"height": 1.8}
    assert body["format"] == "glb" and body["info"]["height_m"] == 1.8
    assert api_env.client.get(f"/v1/characters/{body['id']}", headers=api_env.key("b")).status_code == 404
    r = api_env.client.post("/v1/characters/builtin", headers=h, json={"params": {"height": 2.4}})
    assert r.status_code == 422 and r.json()["detail"] == "invalid body parameters: height: too tall"  # worker's
    r = api_env.client.post("/v1/characters/builtin", headers=h, json={"params": {"height": 3.0, "tail": 1}})
    assert r.status_code == 422 and "params.height" in r.json()["detail"] and "params.tail" in r.json()["detail"]


def test_unsafe_upload_file_names_are_cleaned_or_dropped(api_env: ApiEnv) -> None:
    """"." and ".." name directories; path parts and control characters never reach a stored name or a download."""
    h = api_env.key()
    cases = {".": (None, "motion"), "..": (None, "motion"), "a/..": (None, "motion"), "": (None, "motion"),
             "../../etc/pass\x00wd.bvh": ("passwd.bvh", "passwd"), "c:\\clips\\walk\x1b.bvh": ("walk.bvh", "walk"),
             "\u202eevil.bvh": ("evil.bvh", "evil")}
    for i, (sent, (stored, name)) in enumerate(cases.items()):
        r = api_env.client.post("/v1/motions", params={"filename": sent}, content=BVH + f"#{i}".encode(), headers=h)
        assert r.status_code == 201, (sent, r.text)
        body = r.json()
        assert (body["filename"], body["name"]) == (stored, name), sent
        got = api_env.client.get(f"/v1/motions/{body['id']}/file", headers=h)
        assert got.status_code == 200
        assert f'filename="{stored or "motion.bvh"}"' in got.headers["content-disposition"], sent
    r = upload(api_env, "motions", BVH + b"#multipart", h, "..")
    assert r.status_code == 201 and r.json()["filename"] is None and r.json()["name"] == "motion"
