"""The metrics JSON of a job: pydantic models (the schema), building and writing. Fields: docs/metrics.md."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field

SCHEMA_VERSION: Literal["1.0"] = "1.0"


class Measure(BaseModel):
    """A quantity on the body itself and on the body scaled to 1.80 m tall, with its unit (``null`` when it
    cannot be measured, e.g. contact error without contacts)."""

    value: float | None = Field(description="on the character as it is")
    value_at_180: float | None = Field(description="on the character scaled to 1.80 m tall (papers' convention)")
    unit: str


def measure(value: float | None, factor: float, unit: str, digits: int = 4) -> Measure:
    """A :class:`Measure` of ``value`` (on the body) whose 1.80 m value is ``value * factor``."""
    if value is None or not math.isfinite(value):
        return Measure(value=None, value_at_180=None, unit=unit)
    return Measure(value=round(value, digits), value_at_180=round(value * factor, digits), unit=unit)


class MetricSummary(BaseModel):
    """One number per metric for a whole clip (definitions in docs/metrics.md)."""

    frames: int
    fps: float
    penetration_volume: Measure
    penetration_max_depth: Measure
    penetration_mean_depth: Measure
    penetrating_vertices_percent: float | None
    penetrating_frames_percent: float | None
    penetrating_vertices_percent_by_part: dict[str, float] | None = Field(
        None,
        description="penetrating_vertices_percent split by the part of each penetrating vertex (head, torso, "
        "left_arm, right_arm, left_leg, right_leg): shares of all vertices, adding up to the total",
    )
    deep_frames_percent: float | None = Field(
        None, description="frames whose deepest penetrating vertex is more than 1 cm deep at 1.80 m (this measure's "
        "depths, beyond the bind pose)",
    )
    deep_frames_percent_by_cause: dict[str, float] | None = Field(
        None,
        description="deep_frames_percent split by why (docs/metrics.md 'Deep frames'): pose (a joint rotation could "
        "mend it), placement (held by where the hands and feet are: no elbow or knee turn mends it), fold (a skinning "
        "fold: no rotation mends it)",
    )
    contact_pairs: int
    contact_frames: int
    contact_distance_mean: Measure
    contact_mse: Measure
    contact_satisfied_percent: float | None
    foot_contact_accuracy: float | None
    foot_skate: Measure
    foot_contact_frames: int
    ground_penetration_mean: Measure
    ground_penetration_max: Measure
    global_position_error: Measure
    global_position_mse: Measure
    mpjpe: Measure
    m_c: Measure
    m_i: Measure
    m_o: Measure
    acceleration: Measure
    jerk: Measure
    # Hand contacts (docs/metrics.md "Hand contacts"): each source contact's hand-to-part distance on this body.
    hand_contacts: int = Field(0, description="source contacts (frame, hand, touched part) measured")
    contact_preservation: float | None = Field(
        None, description="share of source contacts whose hand is within 2.5 cm (at 1.80 m) of the touched part"
    )
    contact_hand_distance_mean: Measure = Field(
        default_factory=lambda: Measure(value=None, value_at_180=None, unit="cm"),
        description="mean hand-to-part distance over the source contacts (0 inside, at most 5 cm at 1.80 m)",
    )
    false_contacts: float | None = Field(
        None, description="share of (hand, part, frame) over 5 cm apart on the source that are within 1 cm here"
    )


class Series(BaseModel):
    """One value per frame (``null`` where undefined, e.g. no contact in that frame)."""

    unit: str
    values: list[float | None]


class PenetratingVertices(BaseModel):
    """Vertices deeper than the penetration tolerance, as parallel arrays ``(K,)``: frame, vertex index (into the
    target mesh as written to the GLBs) and depth (cm at 1.80 m); at most ``per_frame_limit`` deepest per frame."""

    frame: list[int]
    vertex: list[int]
    depth: list[float]
    per_frame_limit: int
    truncated: bool = Field(description="some frames had more penetrating vertices than the limit")


class MethodMetrics(BaseModel):
    """Summary and per-frame series of one motion (``before``: the copy baseline; ``after``: the result)."""

    summary: MetricSummary
    series: dict[str, Series] = Field(default_factory=dict)
    penetration_vertices: PenetratingVertices | None = None


class SelfContactEntry(BaseModel):
    """A (hand, other part) pair found in contact on the source, with how many frames and where."""

    hand: str
    other: str
    frames: int
    first: int
    last: int


class ContactVertexPairs(BaseModel):
    """Every vertex pair constrained to touch, as parallel arrays ``(M,)``: frame, the pair on the source body
    (``source_i``, ``source_j``) and its correspondence on the target (``target_i``, ``target_j``)."""

    frame: list[int]
    source_i: list[int]
    source_j: list[int]
    target_i: list[int]
    target_j: list[int]


class SourceContacts(BaseModel):
    """What contact detection found on the source motion."""

    self_contacts: int = Field(0, description="detected (frame, hand, other part) contacts")
    self_contact_frames: int = Field(0, description="frames with at least one hand contact")
    constraints: int = Field(0, description="vertex pairs transferred to the target (3 per contact)")
    pairs: list[SelfContactEntry] = Field(default_factory=list)
    foot_contact_frames: int = Field(0, description="frames where at least one foot joint is planted")
    source_body: str | None = Field(None, description="the body the source was measured on")
    vertex_pairs: ContactVertexPairs | None = None


# --- the source measured on its own body (computed by metrics/source.py) -------------------------------------


class SourceFlag(BaseModel):
    """A source figure over its threshold, with the sentence the job's warnings carry."""

    name: str = Field(description="hand_inside_body, foot_skate, foot_slide, below_floor, floats or jitter")
    value: float
    threshold: float
    unit: str
    message: str


class SourceMetrics(BaseModel):
    """The source motion measured on its own body with the result's measures (docs/metrics.md, "source")."""

    body: str = Field(description="the body the source was measured on")
    frames: int
    fps: float
    penetrating_vertices_percent: float | None
    penetrating_vertices_percent_by_part: dict[str, float] = Field(default_factory=dict)
    penetration_max_depth: Measure
    hand_depth_max: Measure = Field(description="deepest hand vertex inside another part over the clip")
    hand_inside_frames_percent: float = Field(description="frames where a hand is more than 1 cm inside the body")
    hand_inside_frames_percent_by_hand: dict[str, float] = Field(default_factory=dict)
    foot_skate: Measure = Field(description="mean horizontal step of planted foot joints (source foot contacts)")
    foot_slide: Measure = Field(description="mean horizontal step of feet flat on the floor")
    foot_slide_frames_percent: float | None = Field(description="floor frames of a foot sliding more than 1 cm/frame")
    ground_penetration_mean: Measure = Field(description="mean over frames of the lowest vertex below y = 0")
    ground_below_frames_percent: float = Field(description="frames whose lowest vertex is more than 1 cm below y = 0")
    foot_float_mean: Measure = Field(description="mean height of the lowest foot vertex on frames with a planted toe")
    jerk: Measure = Field(description="mean joint jerk at 30 fps (cm/frame^3)")
    jerk_to_acceleration: float | None = Field(None, description="mean jerk over mean acceleration (noise: 1.83)")
    flags: list[SourceFlag] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list, description="the flags' messages (also in the report's notes)")


class MeshRole(BaseModel):
    """One mesh of the target and the role decided for it (docs/meshes.md)."""

    name: str
    role: Literal["body", "accessory"] = Field(description="body: measured; accessory: follows the skin, not tested")
    reason: str = Field(description="the rule that decided")
    vertices: int
    faces: int


class MetricsReport(BaseModel):
    """The metrics JSON of one job (motion x target)."""

    schema_version: Literal["1.0"] = SCHEMA_VERSION
    motion: str
    target: str
    frames: int
    fps: float
    target_height_m: float
    scale_to_180: float = Field(description="multiply a length on the target by this to get it at 1.80 m")
    source_contacts: SourceContacts = Field(default_factory=SourceContacts)
    source: SourceMetrics | None = Field(None, description="the source on its own body (what came in broken)")
    meshes: list[MeshRole] = Field(
        default_factory=list, description="the target's meshes and their roles (accessories are not measured)"
    )
    before: MethodMetrics
    after: MethodMetrics | None = None
    improvement: dict[str, float | None] = Field(
        default_factory=dict, description="after minus before of the main summary numbers at 1.80 m"
    )
    timings_s: dict[str, float] = Field(default_factory=dict)
    notes: list[str] = Field(default_factory=list)
    context: dict[str, Any] = Field(default_factory=dict, description="pipeline information (mapping, stages, ...)")


IMPROVEMENT_FIELDS = (
    "penetration_volume", "penetration_max_depth", "contact_distance_mean", "foot_skate", "ground_penetration_mean",
    "m_c",
)  # fmt: skip


def _value_180(summary: MetricSummary, name: str) -> float | None:
    v = getattr(summary, name)
    return v.value_at_180 if isinstance(v, Measure) else v


def build_metrics_report(
    motion: str,
    target: str,
    target_height_m: float,
    before: MethodMetrics,
    after: MethodMetrics | None = None,
    source_contacts: SourceContacts | None = None,
    timings_s: dict[str, float] | None = None,
    notes: list[str] | None = None,
    context: dict[str, Any] | None = None,
    include_series: bool = True,
    source: SourceMetrics | None = None,
    meshes: list[dict[str, Any]] | None = None,
) -> MetricsReport:
    """The report of one job; ``improvement`` holds after minus before for the main numbers (negative is better
    for all of them). ``source``: the source measured on its body; its warnings are added to ``notes``.
    ``meshes``: the target's meshes (:meth:`retarget_core.character.MeshInfo.as_dict`)."""
    if not include_series:
        before = MethodMetrics(summary=before.summary)
        after = MethodMetrics(summary=after.summary) if after is not None else None
    improvement: dict[str, float | None] = {}
    if after is not None:
        for name in IMPROVEMENT_FIELDS:
            a, b = _value_180(after.summary, name), _value_180(before.summary, name)
            improvement[name] = round(a - b, 4) if a is not None and b is not None else None
    return MetricsReport(
        motion=motion,
        target=target,
        frames=before.summary.frames,
        fps=before.summary.fps,
        target_height_m=round(target_height_m, 4),
        scale_to_180=round(1.80 / target_height_m, 6),
        source_contacts=source_contacts or SourceContacts(),
        source=source,
        meshes=[MeshRole.model_validate(m) for m in meshes or []],
        before=before,
        after=after,
        improvement=improvement,
        timings_s=dict(timings_s or {}),
        notes=list(notes or []) + [w for w in (source.warnings if source else []) if w not in (notes or [])],
        context=dict(context or {}),
    )


def write_metrics_json(report: MetricsReport, path: str | Path) -> Path:
    """Write ``report`` as indented JSON (``null`` for missing values); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report.model_dump(mode="json"), indent=1))
    return path


def read_metrics_json(path: str | Path) -> MetricsReport:
    """Read and validate a metrics JSON."""
    return MetricsReport.model_validate_json(Path(path).read_text())


__all__ = [
    "SCHEMA_VERSION",
    "Measure",
    "MeshRole",
    "MethodMetrics",
    "MetricSummary",
    "MetricsReport",
    "SelfContactEntry",
    "Series",
    "SourceContacts",
    "SourceFlag",
    "SourceMetrics",
    "build_metrics_report",
    "measure",
    "read_metrics_json",
    "write_metrics_json",
]
