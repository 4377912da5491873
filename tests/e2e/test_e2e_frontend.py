"""End to end in a real headless Chromium: upload a shared clip and body through the form, wait for the job on the
dashboard, review it in the viewer (three views render a moving character, scrubbing locks all three to the same
frame, charts, keyboard, laptop and wide layouts, share link without the key, read-only review link), and the
single-file GLB viewer.

Runs against the real service (Redis, worker processes, uvicorn serving frontend/dist), with its
Content-Security-Policy in force: every wait_for_function predicate is a function ("() => ..."), since
Playwright turns a bare expression into an eval in the page, which the policy (rightly) forbids. Screenshots are
kept in test-artifacts/e2e/.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from e2e_helpers import (
    LAPTOP,
    VIEWS,
    WIDE,
    boxes_in_viewport,
    bright_fraction,
    changed_fraction,
    overflow,
    red_fraction,
    seek,
    view_frames,
    view_pixels,
)
from metrics_fixture import CONTACT_FIRST, CONTACT_LAST, PENETRATING, SOURCE_FLAG, metrics_with_series
from sqlalchemy import update

from api.db import session_scope, utcnow
from api.models import Job

pytestmark = [pytest.mark.e2e, pytest.mark.service]

CLIP = "motions/cmu/007_03.bvh"
BODY = "characters/mh_male_bulky.glb"
FRAME_END = 40  # a short range keeps the job quick


@dataclass
class FormJob:
    """What the form flow produced and saw."""

    job_id: str
    base_url: str
    key: str
    motion: dict[str, Any]
    character: dict[str, Any]
    motion_card: str
    character_card: str
    upload_log: list[dict[str, Any]]
    dashboard_statuses: list[str] = field(default_factory=list)
    job: dict[str, Any] = field(default_factory=dict)


def open_app(page: Any, base: str, key: str) -> None:
    """Open the app with no key stored, get the key prompt, enter the key."""
    page.goto(f"{base}/#/upload")
    page.wait_for_selector("#api-key")
    assert "Enter your API key" in page.inner_text("main")
    page.fill("#api-key", key)
    page.click(".key-form button[type=submit]")
    page.wait_for_selector("#motion-file", state="attached")


@pytest.fixture(scope="module")
def form_job(e2e_service: Any, api_key: str, shared_data: Path, browser: Any, artifacts: Path) -> FormJob:
    """Upload the shared clip and body through the form, submit a short job, wait for it on the dashboard."""
    base = e2e_service.base_url
    ctx = browser.new_context(viewport=LAPTOP)
    page = ctx.new_page()
    page.set_default_timeout(60_000)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        open_app(page, base, api_key)
        with page.expect_response(lambda r: r.url.endswith("/v1/motions") and r.request.method == "POST") as mr:
            page.set_input_files("#motion-file", str(shared_data / CLIP))
        motion = mr.value.json()
        assert mr.value.status == 201, motion
        with page.expect_response(lambda r: r.url.endswith("/v1/characters") and r.request.method == "POST") as cr:
            page.set_input_files("#target-file", str(shared_data / BODY))
        character = cr.value.json()
        assert cr.value.status == 201, character
        page.wait_for_selector(f'.card[data-phase=ready][data-asset="{motion["id"]}"]')
        page.wait_for_selector(f'.card[data-phase=ready][data-asset="{character["id"]}"]')
        motion_card = page.inner_text(f'.card[data-asset="{motion["id"]}"]')
        character_card = page.inner_text(f'.card[data-asset="{character["id"]}"]')
        upload_log = page.evaluate("window.__uploadLog || []")
        page.fill("input[name=frame_end]", str(FRAME_END))
        page.screenshot(path=str(artifacts / "01-upload-form-laptop.png"), full_page=True)
        assert page.inner_text("[data-act=submit]") == "Submit job"
        page.click("[data-act=submit]")
        page.wait_for_url("**/#/jobs/*/review")
        job_id = page.url.split("#/jobs/")[1].split("/")[0]
        # The dashboard: the job's row turns succeeded while the page polls.
        page.goto(f"{base}/#/jobs")
        row = f'tr[data-job="{job_id}"]'
        page.wait_for_selector(row)
        statuses = []
        for _ in range(240):
            st = page.get_attribute(row, "data-status")
            if not statuses or statuses[-1] != st:
                statuses.append(st)
            if st in ("succeeded", "failed", "canceled"):
                break
            page.wait_for_timeout(250)
        page.screenshot(path=str(artifacts / "02-dashboard-laptop.png"))
        assert statuses[-1] == "succeeded", f"{statuses}: {page.inner_text(row)}"
        job = httpx.get(f"{base}/v1/jobs/{job_id}", headers={"X-API-Key": api_key}).json()
        assert not errors, errors
        return FormJob(job_id, base, api_key, motion, character, motion_card, character_card, upload_log,
                       statuses, job)  # fmt: skip
    finally:
        ctx.close()


def open_review(
    new_page: Any, fj: FormJob, viewport: dict[str, int] = LAPTOP, metrics: dict[str, Any] | None = None
) -> Any:
    """A page on the job's review URL with the key already stored (as a reviewer who has it). ``metrics``: served
    instead of the job's metrics JSON."""
    page = new_page(viewport)
    if metrics is not None:
        body = json.dumps(metrics)
        page.route(f"**/v1/jobs/{fj.job_id}/metrics.json",
                   lambda route: route.fulfill(status=200, content_type="application/json", body=body))  # fmt: skip
    page.goto(f"{fj.base_url}/#/settings")
    page.evaluate("(k) => localStorage.setItem('retarget.apiKey', k)", fj.key)
    page.goto(f"{fj.base_url}/#/jobs/{fj.job_id}/review")
    page.wait_for_selector(".review-grid[data-ready=true]", timeout=90_000)
    return page


def test_upload_form_shows_parsed_files_and_progress(form_job: FormJob) -> None:
    info = form_job.motion["info"]
    card = form_job.motion_card
    assert f"frames\n{info['frames']}" in card or f"frames{info['frames']}" in card.replace("\n", "")
    assert str(info["joint_count"]) in card
    assert "Joint mapping" in card and f"{len(info['mapping']['joints'])} of 22" in card
    for w in info["warnings"]:
        assert w in card
    cinfo = form_job.character["info"]
    assert str(cinfo["vertices"]) in form_job.character_card
    assert "height" in form_job.character_card
    # XHR upload progress: events for both files, ending with every byte sent.
    names = {e["name"] for e in form_job.upload_log}
    assert {"007_03.bvh", "mh_male_bulky.glb"} <= names
    for name in names:
        last = [e for e in form_job.upload_log if e["name"] == name][-1]
        assert last["loaded"] == last["total"] > 0


def test_dashboard_followed_the_job(form_job: FormJob) -> None:
    assert form_job.dashboard_statuses[-1] == "succeeded"
    assert form_job.job["options"]["frame_end"] == FRAME_END
    assert set(form_job.job["results"]) >= {"result_glb", "before_glb", "metrics_json"}


def test_review_views_render_a_moving_character(new_page: Any, form_job: FormJob, artifacts: Path) -> None:
    page = open_review(new_page, form_job)
    hook = page.evaluate("({frames: window.__viewer.frames, fps: window.__viewer.fps, views: window.__viewer.views()})")
    assert hook["frames"] == FRAME_END
    expected = [v for v in VIEWS if v != "source" or "source_glb" in form_job.job["results"]]
    assert [v for v in VIEWS if hook["views"][v]["loaded"]] == expected
    a, b = 3, FRAME_END - 5
    seek(page, a)
    first = {v: view_pixels(page, v) for v in expected}
    page.screenshot(path=str(artifacts / f"03-review-laptop-frame{a}.png"))
    for v in expected:
        page.locator(f'canvas[data-view="{v}"]').screenshot(path=str(artifacts / f"04-view-{v}-frame{a}.png"))
    seek(page, b)
    second = {v: view_pixels(page, v) for v in expected}
    page.screenshot(path=str(artifacts / f"03-review-laptop-frame{b}.png"))
    for v in expected:
        page.locator(f'canvas[data-view="{v}"]').screenshot(path=str(artifacts / f"04-view-{v}-frame{b}.png"))
        lit = bright_fraction(first[v]), bright_fraction(second[v])
        assert min(lit) > 0.01, f"{v} view looks blank: bright pixel share {lit}"
        moved = changed_fraction(first[v], second[v])
        assert moved > 0.003, f"{v} view did not change between frames {a} and {b} ({moved:.4f} of pixels)"
    assert not page.errors, page.errors


def test_scrubbing_moves_all_views_to_the_same_frame(new_page: Any, form_job: FormJob) -> None:
    page = open_review(new_page, form_job)
    for target in (FRAME_END - 1, 7, 0, 23):
        page.fill(".scrubber", str(target))
        page.wait_for_function("(f) => window.__viewer.frame === f", arg=target)
        page.wait_for_function(
            "(f) => Object.values(window.__viewer.views()).filter((v) => v.loaded).every((v) => v.frame === f)",
            arg=target,
        )
        frames = view_frames(page)
        assert set(frames.values()) == {target}, frames
        assert page.get_attribute(".controls-bar", "data-frame") == str(target)
        for chart in page.evaluate("window.__viewer.charts()"):
            assert chart["playhead"] == target, chart
    assert not page.errors, page.errors


def test_keyboard_plays_pauses_and_steps(new_page: Any, form_job: FormJob) -> None:
    page = open_review(new_page, form_job)
    seek(page, 10)
    page.click("body", position={"x": 5, "y": 300})  # focus the page, not a control
    page.keyboard.press("ArrowRight")
    page.wait_for_function("() => window.__viewer.frame === 11")
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowLeft")
    page.wait_for_function("() => window.__viewer.frame === 9")
    page.keyboard.press("Shift+ArrowRight")
    page.wait_for_function("() => window.__viewer.frame === 19")
    assert set(view_frames(page).values()) == {19}
    page.keyboard.press("Home")
    page.wait_for_function("() => window.__viewer.frame === 0")
    page.keyboard.press("Space")
    page.wait_for_function("() => window.__viewer.playing === true")
    page.wait_for_function("() => window.__viewer.frame >= 3", timeout=20_000)
    for _ in range(5):  # frame-locked while playing: every view on the timeline's frame (one JS turn, atomic)
        locked = page.evaluate(
            "(() => { const f = window.__viewer.frame; return Object.values(window.__viewer.views())"
            ".filter((v) => v.loaded).every((v) => v.frame === f); })()"
        )
        assert locked
        page.wait_for_timeout(120)
    page.keyboard.press("Space")
    page.wait_for_function("() => window.__viewer.playing === false")
    stopped = page.evaluate("window.__viewer.frame")
    page.wait_for_timeout(400)
    assert page.evaluate("window.__viewer.frame") == stopped
    page.keyboard.press("End")
    page.wait_for_function(f"() => window.__viewer.frame === {FRAME_END - 1}")
    # The play button does the same as space.
    page.click("[data-act=play]")
    page.wait_for_function("() => window.__viewer.playing === true")
    page.click("[data-act=play]")
    page.wait_for_function("() => window.__viewer.playing === false")
    assert not page.errors, page.errors


def test_charts_show_the_metrics_of_the_job(new_page: Any, form_job: FormJob, artifacts: Path) -> None:
    """The job's metrics carry per-frame series and penetrating vertices: every chart has data and a playhead,
    and the penetrating vertices the metrics list for a frame are painted in the after view."""
    metrics = httpx.get(f"{form_job.base_url}{form_job.job['results']['metrics_json']}",
                        headers={"X-API-Key": form_job.key}).json()  # fmt: skip
    assert metrics["before"]["series"] and metrics["after"]["series"]
    page = open_review(new_page, form_job)
    seek(page, 12)
    charts = page.evaluate("window.__viewer.charts()")
    assert [c["id"] for c in charts] == ["penetration", "contact", "skate"]
    page.locator(".charts").screenshot(path=str(artifacts / "05-charts-real-job.png"))
    pen = charts[0]
    assert pen["hasData"] and pen["points"] > 0 and pen["playhead"] == 12
    # The job's metrics split penetration by body part (chart switch) and measure the source on its body.
    assert pen["parts"] and metrics["after"]["summary"]["penetrating_vertices_percent_by_part"]
    assert metrics["source"]["body"]
    if page.evaluate("window.__viewer.views().source.loaded"):
        flags = int(page.get_attribute('.view[data-view="source"] .source-quality', "data-flags"))
        assert flags == len(metrics["source"]["flags"])
    assert page.locator(".summary-table tbody tr").count() > 0
    # The penetrating vertices listed for a frame are painted: "before" (the copy) on the bulky body penetrates
    # in frame 12 of the walk; "after" paints whatever the collision stage left (often nothing).
    assert page.is_enabled('[data-toggle="penetration"]')
    page.uncheck('[data-toggle="contacts"]')
    seek(page, 13)
    seek(page, 12)
    for side, view in (("before", "before"), ("after", "after")):
        listed = metrics[side]["penetration_vertices"]
        expected = sum(1 for f in listed["frame"] if f == 12)
        if side == "before":
            assert expected > 0, "the copy on the bulky body should penetrate itself in frame 12 of the walk"
        assert page.get_attribute(f'.view[data-view="{view}"]', "data-penetrating") == str(expected), side
    page.screenshot(path=str(artifacts / "05-review-real-penetration.png"))


@pytest.mark.parametrize("series", [False, True], ids=["job-metrics", "fixture-series"])
def test_layouts_laptop_and_wide_without_overflow(
    new_page: Any, form_job: FormJob, artifacts: Path, series: bool
) -> None:
    """The review fits the screen at both sizes (views side by side, transport, charts and summary above the
    fold), with the job's own metrics and with a metrics JSON that has series and a long summary."""
    metrics = metrics_with_series(FRAME_END, 60.0) if series else None
    for name, viewport in (("laptop", LAPTOP), ("wide", WIDE)):
        page = open_review(new_page, form_job, viewport, metrics=metrics)
        seek(page, 15)
        page.screenshot(path=str(artifacts / f"06-review-{name}{'-series' if series else ''}.png"))
        o = overflow(page)
        assert o["sw"] <= o["w"], f"{name}: horizontal overflow {o}"
        # Views, transport bar and charts are on screen, side by side, without scrolling.
        assert not boxes_in_viewport(page, ".view, .controls-bar, .chart"), name
        boxes = [page.locator(f'.view[data-view="{v}"]').bounding_box() for v in VIEWS]
        assert all(b and b["width"] > 250 and b["height"] > 200 for b in boxes), (name, boxes)
        assert boxes[0]["x"] < boxes[1]["x"] < boxes[2]["x"], "views are not side by side"
        for sel in (".controls-bar", ".chart", ".summary"):
            for box in page.locator(sel).all():
                b = box.bounding_box()
                assert b["y"] + b["height"] <= viewport["height"] + 0.5, f"{name}: {sel} is below the fold ({b})"
        for v in VIEWS:
            if page.evaluate("(v) => window.__viewer.views()[v].loaded", v):
                assert bright_fraction(view_pixels(page, v)) > 0.005, f"{name}: {v} view blank"
        assert not page.errors, page.errors
    if series:
        return
    # The dashboard and the form at both sizes, too.
    for name, viewport in (("laptop", LAPTOP), ("wide", WIDE)):
        page = new_page(viewport)
        page.goto(f"{form_job.base_url}/#/settings")
        page.evaluate("(k) => localStorage.setItem('retarget.apiKey', k)", form_job.key)
        for route in ("jobs", "upload"):
            page.goto(f"{form_job.base_url}/#/{route}")
            page.wait_for_timeout(800)
            o = overflow(page)
            assert o["sw"] <= o["w"], f"{route} at {name}: horizontal overflow {o}"
            page.screenshot(path=str(artifacts / f"07-{route}-{name}.png"))


def test_after_differs_from_before_on_a_real_job(new_page: Any, form_job: FormJob, artifacts: Path) -> None:
    """The refinement stages changed the copy: the metrics say what each stage did, the result GLB is another
    motion than the before GLB, and the review page lists the stages with their frames changed."""
    h = {"X-API-Key": form_job.key}
    metrics = httpx.get(f"{form_job.base_url}{form_job.job['results']['metrics_json']}", headers=h).json()
    reports = metrics["context"]["stage_reports"]
    assert "collisions" in reports and reports["collisions"]["frames_changed"] > 0, reports
    assert "collisions" in metrics["context"]["stages_run"]
    before_pen = metrics["before"]["summary"]["penetrating_vertices_percent"]
    after_pen = metrics["after"]["summary"]["penetrating_vertices_percent"]
    assert after_pen < before_pen, (before_pen, after_pen)
    result = httpx.get(f"{form_job.base_url}{form_job.job['results']['result_glb']}", headers=h).content
    before = httpx.get(f"{form_job.base_url}{form_job.job['results']['before_glb']}", headers=h).content
    assert result != before
    page = open_review(new_page, form_job)
    item = page.locator('.stage-reports li[data-stage="collisions"] [data-frames-changed]')
    assert int(item.get_attribute("data-frames-changed")) == reports["collisions"]["frames_changed"]
    row = page.locator('.summary-table tr[data-key="penetrating_vertices_percent"] td')
    assert row.nth(0).inner_text() != row.nth(1).inner_text()
    page.locator(".side-col").screenshot(path=str(artifacts / "05b-stages-real-job.png"))


def test_share_link_opens_the_review_without_leaking_the_key(new_page: Any, form_job: FormJob) -> None:
    page = open_review(new_page, form_job)
    page.click("[data-act=share]")
    page.wait_for_function("() => document.querySelector('.share-note').dataset.url")
    url = page.get_attribute(".share-note", "data-url")
    assert url == f"{form_job.base_url}/#/jobs/{form_job.job_id}/review"
    assert form_job.key not in url and form_job.key not in page.url
    # Another browser without the key: asked for it, then lands on the review.
    other = new_page(LAPTOP)
    other.goto(url)
    other.wait_for_selector("#api-key")
    other.fill("#api-key", "not-a-key")
    other.click(".key-form button[type=submit]")
    other.wait_for_selector('.key-status[data-ok="false"]')
    assert "key" in other.inner_text(".key-status").lower()
    other.goto(url)
    other.wait_for_selector(".banner:not([hidden])")  # the service rejected the stored key: said on every page
    other.goto(f"{form_job.base_url}/#/settings")
    other.fill("#api-key", form_job.key)
    other.click(".key-form button[type=submit]")
    other.wait_for_url("**/#/upload")  # saved and checked with GET /v1/me
    other.goto(url)
    other.wait_for_selector(".review-grid[data-ready=true]", timeout=90_000)
    assert other.evaluate("window.__viewer.jobId") == form_job.job_id


def test_read_only_review_link_opens_without_a_key(new_page: Any, form_job: FormJob, tmp_path: Path) -> None:
    """"Share read-only link" makes a review link; a browser with no key opens #/review/<token> and gets the
    review and its downloads (and no way to make more links)."""
    page = open_review(new_page, form_job)
    page.click("[data-act=readonly]")
    page.wait_for_function("() => document.querySelector('.share-note').dataset.readonly === 'true'")
    url = page.get_attribute(".share-note", "data-url")
    assert url.startswith(f"{form_job.base_url}/#/review/") and form_job.key not in url
    other = new_page(LAPTOP)  # a fresh context: no key in its storage
    other.goto(url)
    other.wait_for_selector(".review-grid[data-ready=true]", timeout=90_000)
    assert other.evaluate("window.__viewer.jobId") == form_job.job_id
    assert other.evaluate("localStorage.getItem('retarget.apiKey')") is None
    assert other.query_selector("[data-act=readonly]") is None and other.query_selector("[data-act=share]") is None
    with other.expect_download() as dl:
        other.click('[data-dl="result_glb"]')
    dl.value.save_as(tmp_path / "r.glb")
    assert (tmp_path / "r.glb").read_bytes()[:4] == b"glTF"
    assert not other.errors, other.errors


def test_download_buttons_give_the_results(new_page: Any, form_job: FormJob, tmp_path: Path) -> None:
    page = open_review(new_page, form_job)
    with page.expect_download() as dl:
        page.click('[data-dl="result_glb"]')
    path = tmp_path / dl.value.suggested_filename
    dl.value.save_as(path)
    assert dl.value.suggested_filename == f"{form_job.job_id}-result.glb"
    data = path.read_bytes()
    assert data[:4] == b"glTF"
    with page.expect_download() as dl2:
        page.click('[data-dl="metrics_json"]')
    dl2.value.save_as(tmp_path / "m.json")
    assert isinstance(json.loads((tmp_path / "m.json").read_text()), dict)


def js_number(v: float) -> str:
    """The viewer's formatNumber (frontend/src/format.js) for values in the range the fixture uses."""
    if v == 0:
        return "0"
    if abs(v) >= 1000:
        return f"{v:.0f}"
    if abs(v) >= 100:
        return f"{v:.1f}"
    return f"{float(f'{v:.3g}'):g}"


def test_charts_summary_and_markers_with_series(new_page: Any, form_job: FormJob, artifacts: Path) -> None:
    """The chart, summary and marker code against a metrics JSON that has per-frame series (built with the
    schema's pydantic models), on the real job's GLBs."""
    frames = FRAME_END
    data = metrics_with_series(frames, 60.0)
    page = open_review(new_page, form_job, metrics=data)
    charts = {c["id"]: c for c in page.evaluate("window.__viewer.charts()")}
    keys = {"penetration": "penetration_max_depth", "contact": "contact_distance", "skate": "foot_skate"}
    for cid, key in keys.items():
        n = sum(v is not None for m in ("before", "after") for v in data[m]["series"][key]["values"])
        assert charts[cid]["hasData"] and charts[cid]["points"] == n, (cid, charts[cid], n)
    assert not page.locator('.no-data[data-no-series="true"]').count()
    # The playhead and the readout follow the timeline.
    seek(page, 12)
    pen = (
        data["before"]["series"]["penetration_max_depth"]["values"][12],
        data["after"]["series"]["penetration_max_depth"]["values"][12],
    )
    readout = page.inner_text('.chart[data-chart="penetration"] .chart-readout')
    assert readout.split("→")[0].strip() == js_number(pen[0]) and readout.split("→")[1].strip() == js_number(pen[1])
    assert all(c["playhead"] == 12 for c in page.evaluate("window.__viewer.charts()"))
    # A click in the middle of a chart jumps to the middle frame.
    box = page.locator('.chart[data-chart="penetration"] canvas').bounding_box()
    pad_left, pad_right = 44, 8
    page.mouse.click(box["x"] + pad_left + 0.5 * (box["width"] - pad_left - pad_right), box["y"] + box["height"] / 2)
    page.wait_for_function("(f) => Math.abs(window.__viewer.frame - f) <= 1", arg=(frames - 1) / 2)
    # Summary numbers, before and after side by side (at 1.80 m), with the change coloured.
    row = page.locator('.summary-table tr[data-key="penetration_max_depth"]')
    cells = row.locator("td").all_inner_texts()
    b180 = data["before"]["summary"]["penetration_max_depth"]["value_at_180"]
    a180 = data["after"]["summary"]["penetration_max_depth"]["value_at_180"]
    assert cells[0] == js_number(b180) and cells[1] == js_number(a180), cells
    assert "better" in row.get_attribute("class")
    assert page.locator('.summary-table tr[data-key="contact_satisfied_percent"]').get_attribute("class") == "better"
    # Contact markers on a contact frame: vertex pairs (3 per frame, 2 points each) in every view, feet in before/after.
    seek(page, CONTACT_FIRST + 2)
    markers = {v: int(page.get_attribute(f'.view[data-view="{v}"]', "data-markers")) for v in VIEWS
               if page.evaluate("(v) => window.__viewer.views()[v].loaded", v)}  # fmt: skip
    assert markers["before"] >= 6 + 2 and markers["after"] >= 6 + 2, markers
    if "source" in markers:
        assert markers["source"] == 6, markers
    seek(page, CONTACT_LAST + 5)
    after_no_contact = int(page.get_attribute('.view[data-view="after"]', "data-markers"))
    assert after_no_contact == 2, after_no_contact  # only the two planted foot joints of one side
    # Penetrating vertices painted red on the frames that list them (contact markers off: they are red too).
    page.uncheck('[data-toggle="contacts"]')
    seek(page, 10)
    assert page.get_attribute('.view[data-view="after"]', "data-penetrating") == str(PENETRATING["after"])
    assert page.get_attribute('.view[data-view="before"]', "data-penetrating") == str(PENETRATING["before"])
    red_on = {v: red_fraction(page, v) for v in ("before", "after")}
    page.screenshot(path=str(artifacts / "08-review-fixture-penetration-frame10.png"))
    seek(page, 11)
    assert page.get_attribute('.view[data-view="after"]', "data-penetrating") == "0"
    red_off = {v: red_fraction(page, v) for v in ("before", "after")}
    for v in ("before", "after"):  # the listed vertices (indices 0..N) cover a pose-dependent area of the
        # real job's character: 0.19-1 % of the pixels on frame 10; none on a frame that lists none
        assert red_on[v] > 0.001 and red_off[v] < red_on[v] / 5, (v, red_on, red_off)
    # Each view paints its own list (before lists more vertices than after), even when the two files are equal.
    assert red_on["before"] > 1.3 * red_on["after"], red_on
    seek(page, CONTACT_FIRST + 2)
    assert page.get_attribute('.view[data-view="after"]', "data-markers") == "0"
    page.check('[data-toggle="contacts"]')
    page.check('[data-toggle="skeleton"]')
    seek(page, CONTACT_FIRST + 3)
    page.screenshot(path=str(artifacts / "08-review-fixture-series-laptop.png"))
    page.locator(".charts").screenshot(path=str(artifacts / "08-charts-fixture-series.png"))
    # The penetration chart's split by body part: one line per part; the readout names the parts at the frame.
    chart = '.chart[data-chart="penetration"]'
    assert page.get_attribute(chart, "data-mode") == "value"
    page.click(f"{chart} .chart-mode")
    assert page.get_attribute(chart, "data-mode") == "parts"
    assert "by part" in page.inner_text(f"{chart} .chart-title")
    seek(page, 12)
    readout = page.inner_text(f"{chart} .chart-readout")
    assert "head" in readout and "left arm" in readout and "torso" not in readout, readout
    page.locator(".charts").screenshot(path=str(artifacts / "08-charts-fixture-by-part.png"))
    page.click(f"{chart} .chart-mode")
    assert page.get_attribute(chart, "data-mode") == "value"
    head_row = page.locator('.summary-table tr[data-key="penetrating_vertices_percent_by_part.head"]')
    assert head_row.count() == 1 and "head" in head_row.inner_text()
    # What came in broken: the source pane lists the source's flags.
    if page.evaluate("window.__viewer.views().source.loaded"):
        pane = page.locator('.view[data-view="source"] .source-quality')
        assert pane.get_attribute("data-flags") == "1"
        item = pane.locator('[data-flag="hand_inside_body"]')
        assert item.get_attribute("title") == SOURCE_FLAG and "hand inside the body: 35" in item.inner_text()
        page.locator('.view[data-view="source"]').screenshot(path=str(artifacts / "08-source-pane-flags.png"))
    assert not page.errors, page.errors


def test_single_file_viewer_validates_and_plays(
    new_page: Any, form_job: FormJob, tmp_path: Path, artifacts: Path
) -> None:
    glb = httpx.get(f"{form_job.base_url}{form_job.job['results']['result_glb']}", headers={"X-API-Key": form_job.key})
    page = new_page(LAPTOP)
    page.goto(f"{form_job.base_url}/#/view")  # no key needed: nothing is uploaded
    # Dropped on the page (a real DataTransfer with the file in it).
    data = base64.b64encode(glb.content).decode()
    transfer = page.evaluate_handle(
        """(b64) => { const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
            const dt = new DataTransfer(); dt.items.add(new File([bytes], 'result.glb')); return dt; }""",
        data,
    )
    page.dispatch_event("[data-drop=file]", "drop", {"dataTransfer": transfer})
    page.wait_for_selector(".validation[data-done]", timeout=60_000)
    assert page.get_attribute(".validation", "data-done") == "valid", page.inner_text(".validation")
    assert page.get_attribute(".validation-summary", "data-errors") == "0"
    page.wait_for_selector('.view[data-view="file"][data-loaded="true"]')
    page.wait_for_function("() => window.__fileviewer && window.__fileviewer.timeline.frames > 1")
    assert page.evaluate("window.__fileviewer.timeline.frames") == FRAME_END
    page.keyboard.press("End")
    page.wait_for_function(f"() => window.__fileviewer.view.frame === {FRAME_END - 1}")
    page.screenshot(path=str(artifacts / "09-glb-viewer-valid.png"))
    # A damaged file: the validator's errors are listed.
    bad = tmp_path / "broken.glb"
    bad.write_bytes(glb.content[: len(glb.content) // 3])
    page.set_input_files("#glb-file", str(bad))
    page.wait_for_function("() => document.querySelector('.validation').dataset.done === 'invalid'", timeout=60_000)
    assert int(page.get_attribute(".validation-summary", "data-errors")) > 0
    assert page.locator("table.issues tr.sev-error").count() > 0
    page.screenshot(path=str(artifacts / "09-glb-viewer-broken.png"))
    assert not [e for e in page.errors if "pageerror" in e], page.errors


def test_batch_from_the_form_and_errors_in_words(
    e2e_service: Any, new_page: Any, form_job: FormJob, shared_data: Path, artifacts: Path
) -> None:
    """Several targets make a batch (already uploaded assets picked from the lists, one more body dropped in); the
    batch page shows the motions x characters grid live; a failed job's error reads as words on the dashboard and
    on its review URL."""
    page = new_page(LAPTOP)
    page.goto(f"{form_job.base_url}/#/settings")
    page.evaluate("(k) => localStorage.setItem('retarget.apiKey', k)", form_job.key)
    page.goto(f"{form_job.base_url}/#/upload")
    motion_pick = "[data-kind=motion] select[data-pick=existing]"
    page.wait_for_selector(f'{motion_pick} option[value="{form_job.motion["id"]}"]', state="attached")
    page.select_option(motion_pick, form_job.motion["id"])
    page.select_option("[data-kind=target] select[data-pick=existing]", form_job.character["id"])
    page.set_input_files("#target-file", str(shared_data / "characters/mh_female_skinny.glb"))
    page.wait_for_selector("[data-cards=target] .card[data-phase=ready] >> nth=1")
    assert page.locator("[data-cards=motion] .card[data-phase=ready]").count() == 1
    page.fill("input[name=frame_end]", "20")
    page.fill("input[name=batch_name]", "e2e batch")
    assert page.inner_text("[data-act=submit]") == "Submit batch of 2 jobs"
    page.click("[data-act=submit]")
    page.wait_for_url("**/#/batches/*")
    page.wait_for_function("() => document.querySelectorAll('.batch-grid td[data-job]').length === 2")
    page.wait_for_function(
        "() => [...document.querySelectorAll('.batch-grid td[data-job]')].every((td) => td.dataset.status === 'succeeded')",
        timeout=120_000,
    )
    assert "e2e batch" in page.inner_text(".batch")
    page.screenshot(path=str(artifacts / "10-batch-laptop.png"))
    # A frame range past the end of the clip is refused at submission, in words.
    r = httpx.post(f"{form_job.base_url}/v1/jobs", headers={"X-API-Key": form_job.key}, json={
        "motion_id": form_job.motion["id"], "target_character_id": form_job.character["id"],
        "options": {"frame_start": form_job.motion["info"]["frames"] + 50},
    })  # fmt: skip
    assert r.status_code == 422 and "past its end" in r.json()["detail"], r.text
    # A job that failed on its input in the worker, recorded as a worker records it (on the gpu queue, which no
    # worker serves here, it waits until then).
    r = httpx.post(f"{form_job.base_url}/v1/jobs", headers={"X-API-Key": form_job.key}, json={
        "motion_id": form_job.motion["id"], "target_character_id": form_job.character["id"], "queue": "gpu",
        "options": {"frame_end": 20},
    })  # fmt: skip
    assert r.status_code == 202, r.text
    failed = r.json()["id"]
    with session_scope(e2e_service.database_url) as s:
        s.execute(update(Job).where(Job.id == failed).values(
            status="failed", error_kind="input", finished_at=utcnow(),
            message=f"{form_job.motion['filename']}: the joint mapping found no left hand in the motion"))
    page.goto(f"{form_job.base_url}/#/jobs?status=failed")
    row = f'tr[data-job="{failed}"][data-status="failed"]'
    page.wait_for_selector(row, timeout=60_000)
    text = page.inner_text(row)
    message = httpx.get(f"{form_job.base_url}/v1/jobs/{failed}", headers={"X-API-Key": form_job.key}).json()["message"]
    assert message and message in text and "fix them and submit again" in text
    assert page.locator(f"{row} [data-retry]").count() == 1
    page.screenshot(path=str(artifacts / "11-dashboard-failed-laptop.png"))
    page.goto(f"{form_job.base_url}/#/jobs/{failed}/review")
    page.wait_for_selector('.job-card[data-status="failed"]')
    assert message in page.inner_text(".job-card")
    assert not page.errors, page.errors


def test_review_without_a_source_view(new_page: Any, form_job: FormJob) -> None:
    """A job without source.glb (older runs): the source view says so, before and after still play frame-locked."""
    page = new_page(LAPTOP)

    def strip_source(route: Any) -> None:
        job = route.fetch().json()
        job["results"].pop("source_glb", None)
        route.fulfill(status=200, content_type="application/json", body=json.dumps(job))

    page.route(f"**/v1/jobs/{form_job.job_id}", strip_source)
    page.goto(f"{form_job.base_url}/#/settings")
    page.evaluate("(k) => localStorage.setItem('retarget.apiKey', k)", form_job.key)
    page.goto(f"{form_job.base_url}/#/jobs/{form_job.job_id}/review")
    page.wait_for_selector(".review-grid[data-ready=true]", timeout=90_000)
    assert page.get_attribute('.view[data-view="source"]', "data-loaded") == "false"
    assert "no source view for this job" in page.inner_text('.view[data-view="source"]')
    assert page.locator('[data-dl="source_glb"]').count() == 0
    seek(page, 17)
    assert view_frames(page) == {"before": 17, "after": 17}
    assert bright_fraction(view_pixels(page, "after")) > 0.01
    assert not page.errors, page.errors
