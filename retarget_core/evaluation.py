"""Measuring jobs and the evaluation table (``retarget eval``).

- :func:`detect_source_contacts`: hand self-contacts and foot contacts of the source motion on its body.
- :func:`measure_job`: the metrics report of one motion x target from the motions the pipeline made (the
  source on its body, "before" and optionally "after" on the target).
- :func:`run_evaluation`: methods x motions x bodies, a table split into skinny / medium / bulky bodies and
  contact / no-contact clips like paper 1's appendix D, printed and written as JSON and Markdown.

Methods are functions ``(source: LoadedMotion, target: LoadedCharacter) -> Motion`` registered in
:data:`METHODS` by name; ``copy`` (the baseline) is built in and is always measured first, because every other
method's MPJPE and M_i / M_o are measured against it.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, Field

from retarget_core.body_parts import BodyParts, body_parts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import (
    ContactConstraints,
    build_correspondence,
    no_contacts,
    transfer_contacts,
)
from retarget_core.contacts.foot_contact import FootContacts, detect_foot_contacts
from retarget_core.contacts.self_contact import SelfContacts, detect_self_contacts
from retarget_core.energy.sdf import PartSDF, build_part_sdf
from retarget_core.loading import LoadedCharacter, LoadedMotion, load_character, load_motion
from retarget_core.metrics.compute import ClipMeasures, compute_metrics
from retarget_core.metrics.report import (
    ContactVertexPairs,
    MetricsReport,
    SelfContactEntry,
    SourceContacts,
    build_metrics_report,
)
from retarget_core.metrics.source import measure_source
from retarget_core.motion import Motion

Method = Callable[[LoadedMotion, LoadedCharacter], Motion]


def _copy_method(source: LoadedMotion, target: LoadedCharacter) -> Motion:
    from retarget_core.copy_retarget import copy_retarget

    return copy_retarget(source.motion, source.mapping, target.character.skeleton, target.mapping)


METHODS: dict[str, Method] = {"copy": _copy_method}


def register_method(name: str, method: Method) -> None:
    """Make ``method`` available to :func:`run_evaluation` under ``name``."""
    METHODS[name] = method


# --- per-character precomputation, cached -------------------------------------------------------------------

_SDF_CACHE: OrderedDict[str, tuple[BodyParts, PartSDF]] = OrderedDict()
SDF_CACHE_SIZE = 16


def character_key(character: Character, mapping: JointMapping) -> str:
    """A content hash of the mesh, skin and mapping (the same body read twice has the same key)."""
    h = hashlib.sha1()
    for t in (character.vertices, character.faces, character.skin_joints, character.skin_weights):
        h.update(t.detach().contiguous().numpy().tobytes())
    h.update(json.dumps(sorted(mapping.joints.items())).encode())
    return h.hexdigest()


def part_sdf_for(character: Character, mapping: JointMapping) -> tuple[BodyParts, PartSDF]:
    """The body parts and signed-distance grids of ``character`` (built once per body and process)."""
    key = character_key(character, mapping)
    if key in _SDF_CACHE:
        _SDF_CACHE.move_to_end(key)
        return _SDF_CACHE[key]
    parts = body_parts(character, mapping)
    value = (parts, build_part_sdf(character, parts))
    _SDF_CACHE[key] = value
    while len(_SDF_CACHE) > SDF_CACHE_SIZE:
        _SDF_CACHE.popitem(last=False)
    return value


# --- one job ------------------------------------------------------------------------------------------------

MEASURE_THREADS = 1
"""Torch intra-op threads while measuring. The queries are many small tensor operations; on a small, shared
CPU (2 cores, other processes running) OpenMP's parallel regions cost more than they save: a 300-frame job
took 22 s with torch's default 2 threads and 5 s with 1 (benchmarks/results/metrics_benchmark*.json)."""


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (None: leave as is), restoring the setting after."""
    if n is None or n == torch.get_num_threads():
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@dataclass
class SourceContactResult:
    """Contacts found on the source: hand self-contacts (on the source body's vertices) and foot contacts."""

    self_contacts: SelfContacts
    feet: FootContacts
    body_name: str


def detect_source_contacts(body: Character, mapping: JointMapping, motion: Motion) -> SourceContactResult:
    """Contacts of ``motion`` (on ``body``'s skeleton, e.g. the copy of the source onto its body)."""
    parts = body_parts(body, mapping)
    grot, gpos = motion.global_transforms()
    with torch.no_grad():
        posed = body.pose_vertices(grot, gpos)
    self_contacts = detect_self_contacts(parts, posed, body.height, motion.fps)
    _, rest = body.skeleton.rest_global()
    feet = detect_foot_contacts(gpos, rest, mapping, body.height, motion.fps)
    return SourceContactResult(self_contacts, feet, body.name)


def source_contacts_model(found: SourceContactResult, constraints: ContactConstraints) -> SourceContacts:
    """The ``source_contacts`` section of the report."""
    sc = found.self_contacts
    frame, si, sj = sc.vertex_pairs()
    pairs = ContactVertexPairs(
        frame=frame.tolist(), source_i=si.tolist(), source_j=sj.tolist(),
        target_i=constraints.i.tolist(), target_j=constraints.j.tolist(),
    )  # fmt: skip
    return SourceContacts(
        self_contacts=sc.count,
        self_contact_frames=int(sc.frames_with_contact().sum()),
        constraints=constraints.count,
        pairs=[SelfContactEntry.model_validate(e) for e in sc.summary()],
        foot_contact_frames=int(found.feet.labels.any(-1).sum()),
        source_body=found.body_name,
        vertex_pairs=pairs if constraints.count == len(pairs.frame) else None,
    )


@dataclass
class JobMeasurement:
    """Everything measured for one motion x target."""

    report: MetricsReport
    source: SourceContactResult
    constraints: ContactConstraints
    before: ClipMeasures
    after: ClipMeasures | None


def measure_job(
    source_body: Character,
    source_mapping: JointMapping,
    source_view: Motion,
    target: Character,
    target_mapping: JointMapping,
    before: Motion,
    after: Motion | None = None,
    *,
    reference: Motion | None = None,
    source_contacts: SourceContactResult | None = None,
    include_series: bool = True,
    context: dict[str, Any] | None = None,
    notes: list[str] | None = None,
    threads: int | None = MEASURE_THREADS,
    measure_source_motion: bool = True,
) -> JobMeasurement:
    """Detect contacts on the source (unless given), carry them to the target, and measure "before" (and
    "after", against "before") on the target; ``reference`` is a ground-truth motion on the target if any.
    All motions must have the same frame count (the pipeline's motions do). ``threads``: torch threads
    while measuring (see :data:`MEASURE_THREADS`; None keeps the current setting). ``measure_source_motion``:
    also measure the source on its own body (the report's ``source``, its warnings in ``notes``)."""
    with torch_threads(threads):
        return _measure_job(
            source_body, source_mapping, source_view, target, target_mapping, before, after, reference,
            source_contacts, include_series, context, notes, measure_source_motion,
        )  # fmt: skip


def _measure_job(
    source_body: Character,
    source_mapping: JointMapping,
    source_view: Motion,
    target: Character,
    target_mapping: JointMapping,
    before: Motion,
    after: Motion | None,
    reference: Motion | None,
    source_contacts: SourceContactResult | None,
    include_series: bool,
    context: dict[str, Any] | None,
    notes: list[str] | None,
    measure_source_motion: bool = True,
) -> JobMeasurement:
    lengths = {"source view": source_view.num_frames, "before": before.num_frames}
    if after is not None:
        lengths["after"] = after.num_frames
    if reference is not None:
        lengths["reference"] = reference.num_frames
    if len(set(lengths.values())) != 1:
        raise ValueError(f"the motions to measure must have the same number of frames, got {lengths}")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    found = source_contacts or detect_source_contacts(source_body, source_mapping, source_view)
    timings["contacts"] = time.perf_counter() - t
    t = time.perf_counter()
    if found.self_contacts.count:
        corr = build_correspondence(source_body, source_mapping, target, target_mapping)
        constraints = transfer_contacts(found.self_contacts, corr)
    else:
        constraints = no_contacts(source_view.num_frames)
    timings["correspondence"] = time.perf_counter() - t
    t = time.perf_counter()
    _, sdf = part_sdf_for(target, target_mapping)
    timings["sdf"] = time.perf_counter() - t
    t = time.perf_counter()
    ref_measures = None
    if reference is not None:
        _, ref_measures = compute_metrics(target, target_mapping, sdf, reference)
    before_metrics, before_measures = compute_metrics(
        target, target_mapping, sdf, before, contacts=constraints, reference=ref_measures, source_feet=found.feet
    )
    after_metrics, after_measures = None, None
    if after is not None:
        after_metrics, after_measures = compute_metrics(
            target, target_mapping, sdf, after, contacts=constraints, original=before_measures,
            reference=ref_measures, source_feet=found.feet,
        )  # fmt: skip
    timings["metrics"] = time.perf_counter() - t
    t = time.perf_counter()
    source = measure_source(source_body, source_mapping, source_view, part_sdf_for(source_body, source_mapping)[1],
                            found.feet)[0] if measure_source_motion else None  # fmt: skip
    timings["source"] = time.perf_counter() - t
    report = build_metrics_report(
        before.name, target.name, target.height, before_metrics, after_metrics, source_contacts_model(found, constraints),
        {k: round(v, 4) for k, v in timings.items()}, notes, context, include_series, source,
    )  # fmt: skip
    return JobMeasurement(report, found, constraints, before_measures, after_measures)


# --- the evaluation table -----------------------------------------------------------------------------------

TABLE_METRICS: tuple[tuple[str, str], ...] = (
    ("penetration_volume", "pen. vol. cm^3"),
    ("penetration_max_depth", "pen. max cm"),
    ("penetrating_vertices_percent", "pen. verts %"),
    ("m_c", "M_c cm^2"),
    ("contact_distance_mean", "contact err cm"),
    ("contact_satisfied_percent", "contacts kept %"),
    ("foot_contact_accuracy", "foot acc."),
    ("foot_skate", "skate cm/fr"),
    ("mpjpe", "MPJPE cm"),
)


class BodyInfo(BaseModel):
    name: str
    height_m: float
    bulk_index: float = Field(description="mesh volume / height^3 (higher is bulkier)")
    group: str = Field(description="skinny, medium or bulky")


class ClipInfo(BaseModel):
    name: str
    frames: int
    fps: float
    contact_frames: int = Field(description="frames with a hand self-contact on the source body")
    group: str = Field(description="contact or no-contact")
    contacts: list[dict[str, Any]] = Field(default_factory=list, description="(hand, other part, frames) found")


class EvalRow(BaseModel):
    method: str
    body: str
    clip: str
    values: dict[str, float | None] = Field(description="summary metrics at 1.80 m")


class EvalGroup(BaseModel):
    method: str
    bodies: str
    clips: str
    jobs: int
    values: dict[str, float | None] = Field(description="means over the jobs of the group (nulls left out)")


class EvalTable(BaseModel):
    """Result of :func:`run_evaluation`."""

    methods: list[str]
    metrics: list[str]
    labels: dict[str, str]
    bodies: list[BodyInfo]
    clips: list[ClipInfo]
    rows: list[EvalRow]
    groups: list[EvalGroup]
    per_body: list[EvalGroup]
    seconds: float
    settings: dict[str, Any] = Field(default_factory=dict)

    def to_markdown(self) -> str:
        """The grouped tables as Markdown (values at a 1.80 m character)."""
        cols = [m for m in self.metrics]
        head = "| method | bodies | clips | jobs | " + " | ".join(self.labels[c] for c in cols) + " |"
        sep = "|" + "---|" * (4 + len(cols))

        def line(g: EvalGroup) -> str:
            return (
                f"| {g.method} | {g.bodies} | {g.clips} | {g.jobs} | "
                + " | ".join(_fmt(g.values.get(c)) for c in cols)
                + " |"
            )

        out = ["## By body group and clip group (values at 1.80 m)", "", head, sep]
        out += [line(g) for g in self.groups]
        out += ["", "## By body, all clips (bodies from skinny to bulky)", "", head, sep]
        out += [line(g) for g in self.per_body]
        out += ["", "## Bodies", "", "| body | height m | bulk index | group |", "|---|---|---|---|"]
        out += [f"| {b.name} | {b.height_m:.3f} | {b.bulk_index:.4f} | {b.group} |" for b in self.bodies]
        out += [
            "",
            "## Clips",
            "",
            "| clip | frames | fps | contact frames | group | main contacts (frames) |",
            "|---|---|---|---|---|---|",
        ]
        out += [
            f"| {c.name} | {c.frames} | {c.fps:g} | {c.contact_frames} | {c.group} | "
            + ", ".join(f"{e['hand']}-{e['other']} ({e['frames']})" for e in c.contacts[:3])
            + " |"
            for c in self.clips
        ]
        return "\n".join(out) + "\n"


def _fmt(v: float | None) -> str:
    if v is None:
        return "-"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"


def _summary_values(report: MetricsReport, method: str) -> dict[str, float | None]:
    metrics = report.before if method == "copy" else report.after
    assert metrics is not None
    out: dict[str, float | None] = {}
    for name, _ in TABLE_METRICS:
        v = getattr(metrics.summary, name)
        out[name] = v.value_at_180 if hasattr(v, "value_at_180") else v
    return out


def _mean_values(rows: list[EvalRow]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for name, _ in TABLE_METRICS:
        vals = [r.values[name] for r in rows if r.values.get(name) is not None]
        out[name] = round(sum(vals) / len(vals), 4) if vals else None  # type: ignore[arg-type]
    return out


def bulk_groups(indices: list[float]) -> list[str]:
    """By rank of bulk index: the lowest third (rounded) "skinny", the highest third "bulky", the rest
    "medium" (7 bodies: 2, 3, 2; 6 bodies: 2, 2, 2 like paper 1's 3 + 3 split into thirds)."""
    n = len(indices)
    k = round(n / 3)
    order = sorted(range(n), key=lambda i: indices[i])
    out = ["medium"] * n
    for rank, i in enumerate(order):
        if rank < k:
            out[i] = "skinny"
        elif rank >= n - k:
            out[i] = "bulky"
    return out


def bulk_index(character: Character) -> float:
    """Volume of the rest mesh over height cubed: a shape measure independent of size."""
    tri = character.vertices[character.faces].double()
    volume = float(torch.einsum("ti,ti->t", tri[:, 0], torch.cross(tri[:, 1], tri[:, 2], dim=-1)).sum().abs() / 6.0)
    return volume / character.height**3


def run_evaluation(
    motions: list[Path],
    bodies: list[str | Path],
    methods: list[str] | None = None,
    out_dir: Path | None = None,
    max_frames: int | None = 300,
    *,
    fps: float | None = 30.0,
    contact_fraction: float = 0.1,
    body_groups: dict[str, str] | None = None,
    log: Callable[[str], None] | None = print,
    threads: int | None = MEASURE_THREADS,
) -> EvalTable:
    """Run ``methods`` (default: copy) on every motion x body and summarise.

    motions: BVH/glTF/FBX files; bodies: character files or ``builtin:<preset>``; ``max_frames``: first frames
    of each clip (after resampling to ``fps``; None: all). Bodies are grouped by bulk index into thirds
    (:func:`bulk_groups`; ``body_groups`` overrides: name -> group); a clip is a contact clip when at least
    ``contact_fraction`` of its frames have a hand self-contact on the source body. Writes ``eval.json`` and
    ``eval.md`` into ``out_dir`` when given. ``threads``: torch threads during the run (see
    :data:`MEASURE_THREADS`)."""
    with torch_threads(threads):
        return _run_evaluation(motions, bodies, methods, out_dir, max_frames, fps, contact_fraction, body_groups, log)


def _run_evaluation(
    motions: list[Path],
    bodies: list[str | Path],
    methods: list[str] | None,
    out_dir: Path | None,
    max_frames: int | None,
    fps: float | None,
    contact_fraction: float,
    body_groups: dict[str, str] | None,
    log: Callable[[str], None] | None,
) -> EvalTable:
    from retarget_core.resample import resample
    from retarget_core.source_body import source_body_for

    started = time.perf_counter()
    methods = list(methods or ["copy"])
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; available: {sorted(METHODS)}")
    order = ["copy"] + [m for m in methods if m != "copy"]
    say = log or (lambda _m: None)

    targets: list[LoadedCharacter] = []
    infos: list[BodyInfo] = []
    for b in bodies:
        loaded = load_character(b)
        targets.append(loaded)
        infos.append(
            BodyInfo(
                name=loaded.character.name,
                height_m=round(loaded.character.height, 4),
                bulk_index=round(bulk_index(loaded.character), 5),
                group="",
            )
        )
    for info, group in zip(infos, bulk_groups([i.bulk_index for i in infos]), strict=True):
        info.group = (body_groups or {}).get(info.name) or group

    rows: list[EvalRow] = []
    clips: list[ClipInfo] = []
    for path in motions:
        source = load_motion(path)
        motion = source.motion
        if fps is not None:
            motion = resample(motion, fps)
        if max_frames is not None:
            motion = motion.slice(0, max_frames)
        source.motion = motion
        if source.source_character is not None:
            body, body_map = source.source_character.character, source.source_character.mapping
        else:
            body, body_map = source_body_for(motion.skeleton, source.mapping)
        from retarget_core.copy_retarget import copy_retarget

        view = copy_retarget(motion, source.mapping, body.skeleton, body_map)
        t = time.perf_counter()
        found = detect_source_contacts(body, body_map, view)
        contact_frames = int(found.self_contacts.frames_with_contact().sum())
        group = (
            "contact" if contact_frames >= contact_fraction * motion.num_frames and contact_frames > 0 else "no-contact"
        )
        pairs = [{k: e[k] for k in ("hand", "other", "frames")} for e in found.self_contacts.summary()[:6]]
        clips.append(
            ClipInfo(
                name=motion.name,
                frames=motion.num_frames,
                fps=motion.fps,
                contact_frames=contact_frames,
                group=group,
                contacts=pairs,
            )
        )
        say(
            f"{motion.name}: {motion.num_frames} frames, {contact_frames} with hand contacts ({group}), contacts {time.perf_counter() - t:.1f}s"
        )
        for target, info in zip(targets, infos, strict=True):
            tc = target.character
            results = {m: METHODS[m](source, target) for m in order}
            t = time.perf_counter()
            copy_measure = measure_job(
                body, body_map, view, tc, target.mapping, results["copy"], source_contacts=found, include_series=False,
                measure_source_motion=False,
            )
            rows.append(
                EvalRow(
                    method="copy", body=info.name, clip=motion.name, values=_summary_values(copy_measure.report, "copy")
                )
            )
            for m in order[1:]:
                job = measure_job(
                    body,
                    body_map,
                    view,
                    tc,
                    target.mapping,
                    results["copy"],
                    results[m],
                    source_contacts=found,
                    include_series=False,
                    measure_source_motion=False,
                )
                rows.append(EvalRow(method=m, body=info.name, clip=motion.name, values=_summary_values(job.report, m)))
            v = rows[-len(order)].values
            say(
                f"  {info.name:>20}: pen. vol. {_fmt(v['penetration_volume'])} cm^3, max {_fmt(v['penetration_max_depth'])} cm ({time.perf_counter() - t:.1f}s)"
            )

    body_group = {i.name: i.group for i in infos}
    clip_group = {c.name: c.group for c in clips}
    groups: list[EvalGroup] = []
    for m in order:
        for bg in ("skinny", "medium", "bulky", "all"):
            for cg in ("contact", "no-contact", "all"):
                sel = [
                    r
                    for r in rows
                    if r.method == m and bg in ("all", body_group[r.body]) and cg in ("all", clip_group[r.clip])
                ]
                if sel:
                    groups.append(EvalGroup(method=m, bodies=bg, clips=cg, jobs=len(sel), values=_mean_values(sel)))
    per_body = [
        EvalGroup(method=m, bodies=i.name, clips="all", jobs=len(sel), values=_mean_values(sel))
        for m in order
        for i in sorted(infos, key=lambda x: x.bulk_index)
        if (sel := [r for r in rows if r.method == m and r.body == i.name])
    ]
    table = EvalTable(
        methods=order,
        metrics=[n for n, _ in TABLE_METRICS],
        labels=dict(TABLE_METRICS),
        bodies=sorted(infos, key=lambda x: x.bulk_index),
        clips=clips,
        rows=rows,
        groups=groups,
        per_body=per_body,
        seconds=round(time.perf_counter() - started, 2),
        settings={"max_frames": max_frames, "fps": fps, "contact_fraction": contact_fraction},
    )
    say(table.to_markdown())
    if out_dir is not None:
        write_eval_table(table, out_dir)
    return table


def write_eval_table(table: EvalTable, out_dir: Path) -> tuple[Path, Path]:
    """``eval.json`` and ``eval.md`` in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    js, md = out_dir / "eval.json", out_dir / "eval.md"
    js.write_text(json.dumps(table.model_dump(mode="json"), indent=1))
    md.write_text("# Evaluation\n\n" + table.to_markdown())
    return js, md


__all__ = [
    "METHODS",
    "EvalTable",
    "bulk_groups",
    "bulk_index",
    "JobMeasurement",
    "SourceContactResult",
    "MEASURE_THREADS",
    "detect_source_contacts",
    "measure_job",
    "torch_threads",
    "part_sdf_for",
    "register_method",
    "run_evaluation",
    "write_eval_table",
]
