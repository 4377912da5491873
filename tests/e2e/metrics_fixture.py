"""A metrics JSON with per-frame series, built with the schema's own models (retarget_core/metrics/report.py), for
the viewer's chart, summary and marker code. Values are synthetic but shaped like real ones (gaps where a series
is undefined, a contact over a frame range, foot contacts as 0/1 labels).

Two optional fields the viewer reads that schema 1.0 does not define yet are added after validation (proposed in
docs/frontend.md): ``source_contacts.vertex_pairs`` and ``<method>.penetration_vertices``.
"""

from __future__ import annotations

import math
from typing import Any

from retarget_core.metrics.report import (
    MethodMetrics,
    MetricsReport,
    MetricSummary,
    SelfContactEntry,
    Series,
    SourceContacts,
    SourceFlag,
    SourceMetrics,
    build_metrics_report,
    measure,
)

CONTACT_FIRST, CONTACT_LAST = 5, 20
PENETRATING = {"before": 4000, "after": 1500}
PARTS = ("head", "torso", "left_arm", "right_arm", "left_leg", "right_leg")
SOURCE_FLAG = "source (as performed by its body fixture body): a hand is more than 1 cm inside the body"


def _source(frames: int, fps: float, scale: float) -> SourceMetrics:
    """A source section with one flag (a hand sunk into the body)."""
    m = lambda v, unit: measure(v, scale, unit)  # noqa: E731
    flag = SourceFlag(name="hand_inside_body", value=35.0, threshold=10.0, unit="% of frames", message=SOURCE_FLAG)
    return SourceMetrics(
        body="fixture body", frames=frames, fps=fps, penetrating_vertices_percent=0.4,
        penetrating_vertices_percent_by_part={p: 0.1 if p in ("left_arm", "torso") else 0.0 for p in PARTS},
        penetration_max_depth=m(2.0, "cm"), hand_depth_max=m(2.0, "cm"), hand_inside_frames_percent=35.0,
        hand_inside_frames_percent_by_hand={"LeftHand": 35.0, "RightHand": 0.0}, foot_skate=m(0.2, "cm/frame"),
        foot_slide=m(0.3, "cm/frame"), foot_slide_frames_percent=2.0, ground_penetration_mean=m(0.1, "cm"),
        ground_below_frames_percent=0.0, foot_float_mean=m(0.3, "cm"), jerk=m(0.2, "cm/frame^3"),
        flags=[flag], warnings=[flag.message],
    )  # fmt: skip  # vertices 0..n-1 listed as penetrating on even frames


def _summary(frames: int, fps: float, scale: float, pen: float, skate: float, contact: float) -> MetricSummary:
    m = lambda v, unit: measure(v, scale, unit)  # noqa: E731
    return MetricSummary(
        frames=frames, fps=fps,
        penetration_volume=m(pen * 12.0, "cm^3"), penetration_max_depth=m(pen, "cm"),
        penetration_mean_depth=m(pen / 2, "cm"), penetrating_vertices_percent=pen / 3,
        penetrating_frames_percent=40.0, contact_pairs=3 * (CONTACT_LAST - CONTACT_FIRST + 1),
        contact_frames=CONTACT_LAST - CONTACT_FIRST + 1, contact_distance_mean=m(contact, "cm"),
        contact_mse=m(contact**2, "cm^2"), contact_satisfied_percent=100.0 - contact * 10,
        foot_contact_accuracy=0.9, foot_skate=m(skate, "cm/frame"), foot_contact_frames=frames // 2,
        ground_penetration_mean=m(0.2, "cm"), ground_penetration_max=m(0.5, "cm"),
        global_position_error=m(None, "cm"), global_position_mse=m(None, "cm^2"), mpjpe=m(1.0, "cm"),
        m_c=m(pen**2, "cm^2"), m_i=m(pen**2 / 2, "cm^2"), m_o=m(0.1, "cm^2"),
        acceleration=m(0.4, "cm/frame^2"), jerk=m(0.2, "cm/frame^3"),
        penetrating_vertices_percent_by_part={**{p: 0.0 for p in PARTS}, "head": pen / 6, "left_arm": pen / 6},
    )  # fmt: skip


def _method(frames: int, fps: float, scale: float, gain: float) -> MethodMetrics:
    pen = [round(gain * 2.0 * (1 + math.sin(i / 4.0)), 4) for i in range(frames)]
    contact = [round(gain * (1.5 + math.cos(i / 3.0)), 4) if CONTACT_FIRST <= i <= CONTACT_LAST else None
               for i in range(frames)]  # fmt: skip
    skate = [None] + [round(gain * 0.3 * (1 + math.sin(i / 2.0)), 4) if i % 10 < 6 else None for i in range(1, frames)]
    left = [1.0 if (i // 10) % 2 == 0 else 0.0 for i in range(frames)]
    right = [1.0 - v for v in left]
    series = {
        "penetration_max_depth": Series(unit="cm at 1.80 m", values=pen),
        "contact_distance": Series(unit="cm at 1.80 m", values=contact),
        "foot_skate": Series(unit="cm/frame at 1.80 m", values=skate),
        "foot_contact_left_toe": Series(unit="0/1", values=left),
        "foot_contact_left_heel": Series(unit="0/1", values=left),
        "foot_contact_right_toe": Series(unit="0/1", values=right),
        "foot_contact_right_heel": Series(unit="0/1", values=right),
        **{f"penetrating_vertices_percent_{p}": Series(unit="%", values=[round(v / 6, 4) if p in ("head", "left_arm") else 0.0
                                                                       for v in pen]) for p in PARTS},
    }  # fmt: skip
    return MethodMetrics(summary=_summary(frames, fps, scale, max(pen), 0.3 * gain, 1.5 * gain), series=series)


def metrics_with_series(frames: int, fps: float, target_height_m: float = 1.73) -> dict[str, Any]:
    """A metrics JSON (schema 1.0) for a clip of ``frames`` frames, plus the proposed optional fields."""
    scale = 1.80 / target_height_m
    before = _method(frames, fps, scale, 1.0)
    after = _method(frames, fps, scale, 0.4)
    contacts = SourceContacts(
        self_contacts=CONTACT_LAST - CONTACT_FIRST + 1, self_contact_frames=CONTACT_LAST - CONTACT_FIRST + 1,
        constraints=3 * (CONTACT_LAST - CONTACT_FIRST + 1),
        pairs=[SelfContactEntry(hand="LeftHand", other="Spine2", frames=CONTACT_LAST - CONTACT_FIRST + 1,
                                first=CONTACT_FIRST, last=CONTACT_LAST)],
        foot_contact_frames=frames, source_body="builtin",
    )  # fmt: skip
    report = build_metrics_report("fixture", "fixture target", target_height_m, before, after, contacts,
                                  notes=["fixture metrics (synthetic series)"],
                                  source=_source(frames, fps, scale))  # fmt: skip
    data = MetricsReport.model_validate(report.model_dump(mode="json")).model_dump(mode="json")
    # Proposed optional fields (not in schema 1.0 yet): contact vertex pairs and penetrating vertices per frame.
    rows = [(f, k) for f in range(CONTACT_FIRST, CONTACT_LAST + 1) for k in range(3)]
    data["source_contacts"]["vertex_pairs"] = {
        "frame": [f for f, _ in rows],
        "source_i": [100 + k for _, k in rows], "source_j": [5000 + k for _, k in rows],
        "target_i": [200 + k for _, k in rows], "target_j": [6000 + k for _, k in rows],
    }  # fmt: skip
    for name, n in PENETRATING.items():
        pen_rows = [(f, v) for f in range(0, frames, 2) for v in range(n)]
        data[name]["penetration_vertices"] = {
            "frame": [f for f, _ in pen_rows], "vertex": [v for _, v in pen_rows], "depth": [0.5 for _ in pen_rows],
        }  # fmt: skip
    return data
