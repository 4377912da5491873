"""One job run in this process: claim, progress, heartbeat, cancel, outcomes, idempotency; the real pipeline."""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import update
from worker_testkit import add_job, store

from api.db import session_scope
from api.models import Job, WebhookDelivery
from api.settings import Settings
from retarget_core.errors import InvalidFileError
from retarget_core.jobs import JobCanceled, JobOutputs
from worker.runner import JobRun, json_safe

HERE = Path(__file__).resolve().parent


def write_outputs(out_dir: Path) -> JobOutputs:
    for name in ("result.glb", "before.glb"):
        (out_dir / name).write_bytes(b"glTF")
    (out_dir / "metrics.json").write_text("{}")
    return JobOutputs(out_dir / "result.glb", out_dir / "before.glb", out_dir / "metrics.json", {"a": 1.0},
                      {"copy": 0.1}, ["w"])


def job(settings: Settings, job_id: str) -> Job:
    with session_scope(settings.resolved_database_url) as s:
        row = s.get(Job, job_id)
        assert row is not None
        return row


def test_success_records_outputs_and_is_idempotent(wsettings: Settings) -> None:
    job_id = add_job(wsettings, callback_url="http://127.0.0.1:9/hook")
    seen: list[tuple[str, float]] = []

    def pipeline(inputs: Any, out_dir: Path, progress: Any, should_cancel: Any) -> JobOutputs:
        assert inputs.target == "builtin:male_average" and inputs.motion_path.name.endswith(".bvh")
        assert job(wsettings, job_id).status == "running"
        progress("read", 0.2)
        seen.append((job(wsettings, job_id).stage, job(wsettings, job_id).progress))
        assert not should_cancel()
        return write_outputs(out_dir)

    result = JobRun(wsettings, job_id, 1, "w1").run(pipeline)
    assert result.outcome == "succeeded" and result.webhook_delivery is not None
    assert seen == [("read", 0.2)]
    row = job(wsettings, job_id)
    assert row.status == "succeeded" and row.progress == 1.0 and row.worker == "w1"
    assert row.outputs == {n: f"jobs/{job_id}/run-1/{n}" for n in ("result.glb", "before.glb", "metrics.json")}
    assert row.summary == {"a": 1.0} and row.stage_seconds == {"copy": 0.1} and row.warnings == ["w"]
    with session_scope(wsettings.resolved_database_url) as s:
        d = s.get(WebhookDelivery, result.webhook_delivery)
        assert d.event == "job.succeeded" and d.status == "pending"
    # a re-delivered message for the finished job does nothing
    assert JobRun(wsettings, job_id, 1, "w2").run(pipeline).outcome == "skipped"
    assert job(wsettings, job_id).worker == "w1"


def test_input_error_is_failed_with_the_users_names(wsettings: Settings) -> None:
    ref = "a" * 64 + ".bvh"
    job_id = add_job(wsettings, motion_ref=ref)

    def pipeline(inputs: Any, out_dir: Path, **_: Any) -> JobOutputs:
        raise InvalidFileError("frame 3 has NaN in channel Xrotation", str(inputs.motion_path))

    assert JobRun(wsettings, job_id, 1, "w").run(pipeline).outcome == "failed"
    row = job(wsettings, job_id)
    assert row.error_kind == "input" and row.message == "the motion: frame 3 has NaN in channel Xrotation"


def test_internal_error_and_missing_outputs(wsettings: Settings) -> None:
    a = add_job(wsettings)

    def boom(*_: Any, **__: Any) -> JobOutputs:
        raise ZeroDivisionError("division by zero")

    assert JobRun(wsettings, a, 1, "w").run(boom).outcome == "failed"
    assert job(wsettings, a).error_kind == "internal"
    assert job(wsettings, a).message == "internal error: ZeroDivisionError: division by zero"
    b = add_job(wsettings)
    assert JobRun(wsettings, b, 1, "w").run(lambda *a, **k: JobOutputs(*(Path("/nope"),) * 3, {}, {}, [])).outcome \
        == "failed"
    assert "did not write result.glb, before.glb, metrics.json" in job(wsettings, b).message


def test_soft_time_limit_is_a_timeout_message(wsettings: Settings) -> None:
    from celery.exceptions import SoftTimeLimitExceeded

    job_id = add_job(wsettings)

    def slow(*_: Any, **__: Any) -> JobOutputs:
        raise SoftTimeLimitExceeded()

    JobRun(wsettings, job_id, 1, "w").run(slow)
    row = job(wsettings, job_id)
    assert row.status == "failed" and row.error_kind == "timeout" and "longer than 1800 s" in row.message


def test_cancel_request_stops_the_pipeline(wsettings: Settings) -> None:
    job_id = add_job(wsettings)

    def pipeline(inputs: Any, out_dir: Path, progress: Any, should_cancel: Any) -> JobOutputs:
        with session_scope(wsettings.resolved_database_url) as s:
            s.execute(update(Job).where(Job.id == job_id).values(cancel_requested=True))
        t = time.monotonic()
        while time.monotonic() - t < 5:
            if should_cancel():
                raise JobCanceled("canceled before stage x")
            time.sleep(0.05)
        raise AssertionError("the cancel request was not seen")

    assert JobRun(wsettings, job_id, 1, "w").run(pipeline).outcome == "canceled"
    assert job(wsettings, job_id).status == "canceled"


def test_heartbeat_runs_and_a_lost_job_writes_nothing(wsettings: Settings) -> None:
    job_id = add_job(wsettings)
    beats: list[Any] = []

    def pipeline(inputs: Any, out_dir: Path, progress: Any, should_cancel: Any) -> JobOutputs:
        first = job(wsettings, job_id).heartbeat_at
        time.sleep(0.7)
        beats.append(job(wsettings, job_id).heartbeat_at > first)
        # the reaper gave the job to another attempt meanwhile
        with session_scope(wsettings.resolved_database_url) as s:
            s.execute(update(Job).where(Job.id == job_id).values(attempt=2, status="queued"))
        time.sleep(0.6)
        progress("copy", 0.5)
        assert should_cancel()
        return write_outputs(out_dir)

    assert JobRun(wsettings, job_id, 1, "w").run(pipeline).outcome == "lost"
    assert beats == [True]
    row = job(wsettings, job_id)
    assert row.status == "queued" and row.attempt == 2 and row.stage == "starting" and row.outputs is None


def test_only_one_of_two_concurrent_claims_wins(wsettings: Settings) -> None:
    job_id = add_job(wsettings)
    results: list[bool] = []
    runs = [JobRun(wsettings, job_id, 1, f"w{i}") for i in range(4)]
    threads = [threading.Thread(target=lambda r=r: results.append(r.claim())) for r in runs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(results) == [False, False, False, True]


def test_json_safe() -> None:
    import numpy as np

    assert json_safe({"a": float("nan"), "b": [np.float32(1.5), (1, "x")], 3: None}) == \
        {"a": None, "b": [1.5, [1, "x"]], "3": None}
    json.dumps(json_safe({"x": float("inf")}), allow_nan=False)


def test_real_pipeline_on_shared_data(sqlite_settings: Settings, shared_data: Path) -> None:
    """The library's run_job through the runner: a valid GLB and a metrics JSON on disk."""
    motion = store(sqlite_settings, shared_data / "motions" / "cmu" / "007_03.bvh")
    target = store(sqlite_settings, shared_data / "characters" / "mh_male_skinny.glb")
    job_id = add_job(sqlite_settings, motion_ref=motion, target_ref=target, options={"frame_end": 30})
    assert JobRun(sqlite_settings, job_id, 1, "w").run().outcome == "succeeded"
    row = job(sqlite_settings, job_id)
    root = sqlite_settings.data_dir.resolve()
    json.loads((root / row.outputs["metrics.json"]).read_text())
    sys.path.insert(0, str(HERE.parent))
    try:
        from gltf_validator import assert_valid_glb
    finally:
        sys.path.remove(str(HERE.parent))
    assert_valid_glb(root / row.outputs["result.glb"])
    assert set(row.stage_seconds) >= {"read", "copy", "write"}


def test_real_pipeline_bad_input_is_an_input_error(sqlite_settings: Settings, tmp_path: Path) -> None:
    bad = tmp_path / "nan.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation "
                   "Xrotation Yrotation\n End Site\n {\n  OFFSET 0 10 0\n }\n}\nMOTION\nFrames: 2\n"
                   "Frame Time: 0.0333\n0 0 0 0 0 0\n0 nan 0 0 0 0\n")
    job_id = add_job(sqlite_settings, motion_ref=store(sqlite_settings, bad))
    assert JobRun(sqlite_settings, job_id, 1, "w").run().outcome == "failed"
    row = job(sqlite_settings, job_id)
    assert row.error_kind == "input" and "the motion" in row.message and "a" * 10 not in row.message


@pytest.mark.parametrize("n", [1])
def test_progress_is_throttled(wsettings: Settings, n: int) -> None:
    wsettings.progress_min_interval_seconds = 10.0
    job_id = add_job(wsettings)
    run = JobRun(wsettings, job_id, 1, "w")
    assert run.claim()
    run.progress("read", 0.1)
    run.progress("read", 0.2)  # same stage, too soon: not written
    assert job(wsettings, job_id).progress == 0.1
    run.progress("copy", 0.3)  # new stage: written
    assert job(wsettings, job_id).stage == "copy" and job(wsettings, job_id).progress == 0.3


def test_job_device_comes_from_the_job_the_worker_or_its_queue(wsettings: Settings) -> None:
    """A job that names no device runs on cuda from the gpu queue, on cpu elsewhere, or on the worker's
    setting; a job's own choice wins."""
    def device_of(settings: Settings, **values: Any) -> str:
        job_id = add_job(settings, **values)
        run = JobRun(settings, job_id, 1, "w1")
        return str(run.inputs(job(settings, job_id)).options.device)

    assert device_of(wsettings) == "cpu"
    gpu_id = add_job(wsettings)
    with session_scope(wsettings.resolved_database_url) as s:
        s.execute(update(Job).where(Job.id == gpu_id).values(queue="gpu"))
    assert str(JobRun(wsettings, gpu_id, 1, "w1").inputs(job(wsettings, gpu_id)).options.device) == "cuda"
    assert device_of(wsettings, options={"device": "cpu"}) == "cpu"
    assert device_of(wsettings.model_copy(update={"worker_device": "auto"})) == "auto"
