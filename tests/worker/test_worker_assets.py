"""Worker side of uploads and bodies with the real library: parse results, error messages, generated bodies."""

from __future__ import annotations

from pathlib import Path

import pytest
from worker_testkit import store

from api.db import session_scope
from api.models import Asset, WorkerCall
from api.settings import Settings
from api.storage import Storage
from worker import assets


def call(settings: Settings) -> str:
    with session_scope(settings.resolved_database_url) as s:
        c = WorkerCall(op="test")
        s.add(c)
        s.flush()
        return c.id


def outcome(settings: Settings, call_id: str) -> WorkerCall:
    with session_scope(settings.resolved_database_url) as s:
        c = s.get(WorkerCall, call_id)
        assert c is not None and c.status != "pending"
        return c


def test_inspect_a_shared_character(sqlite_settings: Settings, shared_data: Path) -> None:
    ref = store(sqlite_settings, shared_data / "characters" / "mh_male_skinny.glb")
    c = call(sqlite_settings)
    assets.run_inspect(sqlite_settings, c, ref, "character", "skinny.glb")
    res = outcome(sqlite_settings, c)
    assert res.status == "ok", res.message
    info = res.result["info"]
    assert info["format"] == "glb" and info["name"] == "skinny" and len(info["joints"]) == 22
    assert 1.5 < info["height_m"] < 2.0


def test_truncated_glb_names_the_file_and_the_problem(sqlite_settings: Settings, shared_data: Path,
                                                       tmp_path: Path) -> None:
    data = (shared_data / "characters" / "mh_male_skinny.glb").read_bytes()
    bad = tmp_path / "cut.glb"
    bad.write_bytes(data[: len(data) // 2])
    ref = store(sqlite_settings, bad)
    c = call(sqlite_settings)
    assets.run_inspect(sqlite_settings, c, ref, "character", "hero.glb")
    res = outcome(sqlite_settings, c)
    assert res.status == "error" and res.message.startswith("hero.glb: ")
    assert ref.split(".")[0] not in res.message and str(sqlite_settings.data_dir) not in res.message


def test_motion_as_character_is_refused(sqlite_settings: Settings, shared_data: Path) -> None:
    ref = store(sqlite_settings, shared_data / "motions" / "cmu" / "007_03.bvh")
    c = call(sqlite_settings)
    assets.run_inspect(sqlite_settings, c, ref, "motion", "walk.bvh")
    assert outcome(sqlite_settings, c).result["info"]["frames"] > 60


def test_make_body_and_bad_params(sqlite_settings: Settings) -> None:
    c = call(sqlite_settings)
    assets.run_make_body(sqlite_settings, c, {"height": 1.8, "weight": 0.9, "name": "heavy"})
    res = outcome(sqlite_settings, c)
    assert res.status == "ok", res.message
    st = Storage(sqlite_settings.data_dir)
    assert st.blob_path(st.blob_ref(res.result["sha256"], "glb")).is_file()
    assert abs(res.result["info"]["height_m"] - 1.8) < 0.02 and res.result["params"]["weight"] == 0.9
    c = call(sqlite_settings)
    assets.run_make_body(sqlite_settings, c, {"height": 9.0, "colour": "red"})
    res = outcome(sqlite_settings, c)
    assert res.status == "error" and res.message.startswith("invalid body parameters: height")


def test_register_builtins(sqlite_settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    import retarget_core.bodies.presets as presets

    monkeypatch.setattr(presets, "list_presets", lambda: ["male_average"])
    with session_scope(sqlite_settings.resolved_database_url) as s:
        s.add(Asset(id="builtin:retired", kind="character", origin="builtin", name="retired", info={}))
    assert assets.register_builtins(sqlite_settings) == ["male_average"]
    with session_scope(sqlite_settings.resolved_database_url) as s:
        a = s.get(Asset, "builtin:male_average")
        assert a is not None and a.owner_id is None and a.format == "glb" and a.info["preset"] == "male_average"
        assert len(a.info["joints"]) == 22 and s.get(Asset, "builtin:retired") is None
        sha = a.sha256
    assets.register_builtins(sqlite_settings)  # idempotent: kept, not made again
    with session_scope(sqlite_settings.resolved_database_url) as s:
        assert s.get(Asset, "builtin:male_average").sha256 == sha


@pytest.mark.timeout(30)
def test_motion_with_a_60000_character_joint_name_is_refused_at_once(sqlite_settings: Settings, samples: Path,
                                                                     tmp_path: Path) -> None:
    """Such a name once took half a minute in the message redaction; now the reader refuses it by its limit."""
    import time

    from retarget_core.io.bvh import MAX_JOINT_NAME_CHARS

    text = (samples / "motions" / "007_03.bvh").read_text()
    hostile = tmp_path / "long.bvh"
    hostile.write_text(text.replace("JOINT CC_Base_L_PinkyToe1\n", "JOINT " + "J" * 60_000 + "\n", 1))
    ref = store(sqlite_settings, hostile)
    c = call(sqlite_settings)
    start = time.perf_counter()
    assets.run_inspect(sqlite_settings, c, ref, "motion", "long.bvh")
    took = time.perf_counter() - start
    res = outcome(sqlite_settings, c)
    assert res.status == "error" and res.message.startswith("long.bvh: "), res.message
    assert f"limit is {MAX_JOINT_NAME_CHARS}" in res.message and took < 5.0, (res.message, took)
