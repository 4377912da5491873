"""The review page's hand focus on a job with fingers: a real MakeHuman body on the Mixamo rig curling its
fingers, retargeted onto one on the Unreal-style rig through the real service; the upload answers list the
fingers; choosing "Left hand" brings every view's camera 0.35 m from that hand and keeps it there while playing."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from retarget_core.copy_retarget import copy_retarget
from retarget_core.io.gltf_write import write_glb
from retarget_core.loading import load_motion
from retarget_core.mapping import map_joints
from retarget_core.motion import Motion
from tests.core.extras_rigs import finger_body
from tests.core.test_extras_pipeline import _curl

pytestmark = [pytest.mark.e2e, pytest.mark.service]
FRAMES = 20


@pytest.fixture(scope="module")
def finger_job(e2e_service: Any, api_key: str, samples: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:  # type: ignore[type-arg]
    tmp = tmp_path_factory.mktemp("hand-focus")
    source = finger_body("female_skinny", "mixamo")
    smap = map_joints(source.skeleton)
    clip = load_motion(samples / "motions" / "007_03.bvh")
    walk = copy_retarget(clip.motion, clip.mapping, source.skeleton, smap)
    walk = Motion(walk.skeleton, walk.fps, walk.rotations[:FRAMES], walk.translations[:FRAMES], "walk")
    write_glb(source, _curl(walk, smap, FRAMES), tmp / "fingers_walk.glb", clip_name="walk")
    write_glb(finger_body("male_bulky", "game_engine"), None, tmp / "fingers_target.glb")
    base, headers = e2e_service.base_url, {"X-API-Key": api_key}
    with httpx.Client(base_url=base, headers=headers, timeout=120) as http:
        motion = http.post("/v1/motions", params={"filename": "fingers_walk.glb"},
                           content=(tmp / "fingers_walk.glb").read_bytes()).json()  # fmt: skip
        with (tmp / "fingers_target.glb").open("rb") as fh:
            character = http.post("/v1/characters", files={"file": ("fingers_target.glb", fh)}).json()
        job = http.post("/v1/jobs", json={"motion_id": motion["id"], "target_character_id": character["id"]}).json()
        for _ in range(600):
            job = http.get(f"/v1/jobs/{job['id']}").json()
            if job["status"] in ("succeeded", "failed", "canceled"):
                break
            time.sleep(0.5)
    assert job["status"] == "succeeded", job
    return {"job": job, "motion": motion, "character": character, "base": base, "key": api_key}


def test_upload_answers_carry_the_finger_mapping(finger_job: dict) -> None:  # type: ignore[type-arg]
    extras = finger_job["character"]["info"]["mapping"]["extras"]
    assert sum(1 for v in extras.values() if v["kind"] == "finger") == 30
    assert extras["LeftHandIndex1"]["joint"] == "index_01_l"
    assert finger_job["motion"]["info"]["mapping"]["extras"]["RightHandThumb3"]["joint"] == "mixamorig:RightHandThumb3"


def test_hand_focus_brings_every_camera_to_the_hand(new_page: Any, finger_job: dict, artifacts: Path) -> None:  # type: ignore[type-arg]
    page = new_page()
    page.goto(f"{finger_job['base']}/#/settings")
    page.evaluate("(k) => localStorage.setItem('retarget.apiKey', k)", finger_job["key"])
    page.goto(f"{finger_job['base']}/#/jobs/{finger_job['job']['id']}/review")
    page.wait_for_selector(".review-grid[data-ready=true]", timeout=90_000)
    whole = page.evaluate("window.__viewer.views()")
    assert all(v["camera"]["distance"] > 1.0 for v in whole.values() if v["loaded"])
    page.select_option("select[data-act=focus]", "LeftHand")
    for frame in (0, FRAMES // 2):
        page.evaluate(f"window.__viewer.seek({frame})")
        page.wait_for_timeout(200)
        views = page.evaluate("window.__viewer.views()")
        loaded = [v for v in views.values() if v["loaded"]]
        assert len(loaded) == 3
        for v in loaded:
            assert v["camera"]["focus"] == "LeftHand" and abs(v["camera"]["distance"] - 0.35) < 1e-3
            assert v["camera"]["offset"] is not None and v["camera"]["offset"] < 1e-3
    page.screenshot(path=str(artifacts / "hand-focus-left.png"))
    page.select_option("select[data-act=focus]", "")
    page.wait_for_timeout(200)
    assert all(v["camera"]["distance"] > 1.0 for v in page.evaluate("window.__viewer.views()").values() if v["loaded"])
    assert not page.errors, page.errors
