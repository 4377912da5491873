"""The evaluation table (``retarget eval``): methods x motions x bodies, split into skinny / medium / bulky
bodies and contact / no-contact clips like paper 1's appendix D, printed and written as JSON and Markdown.

A method is a set of refinement stages (:data:`METHODS`): ``copy`` runs none (the baseline, always measured
first: every other method's MPJPE and M_i / M_o are measured against it). Every job runs through
:func:`retarget_core.pipeline.prepare` and :func:`retarget_core.pipeline.refine`, exactly as a job of the
service or the CLI does.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, Field

from retarget_core.character import Character
from retarget_core.jobs import JobInputs
from retarget_core.loading import load_character
from retarget_core.measure import MEASURE_THREADS, measure_job, torch_threads
from retarget_core.metrics.report import MetricsReport
from retarget_core.options import RetargetOptions
from retarget_core.stages import REFINEMENT_STAGE_NAMES, stage_info

METHODS: dict[str, tuple[str, ...]] = {
    "copy": (),
    "collisions": ("collisions",),
    "foot_lock": ("foot_lock",),
    "collisions+foot_lock": ("collisions", "foot_lock"),
    "full": tuple(n for n in REFINEMENT_STAGE_NAMES if stage_info(n).available),
}
"""Method name -> the refinement stages it runs (``full``: every stage available in this version)."""


def method_options(method: str, fps: float | None) -> RetargetOptions:
    """The job options of ``method``: its refinement stages on, the others off, contacts on."""
    stages = {n: n in METHODS[method] for n in REFINEMENT_STAGE_NAMES}
    return RetargetOptions(fps=fps, stages={"contacts": True, **stages})


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
    source_character: str | Path | None = None,
) -> EvalTable:
    """Run ``methods`` (default: copy) on every motion x body and summarise.

    motions: BVH/glTF/FBX files; bodies: character files or ``builtin:<preset>``; ``max_frames``: first frames
    of each clip (after resampling to ``fps``; None: all); ``source_character``: the body performing the source
    motions (default: the motion file's own mesh, or a built-in body sized to the source skeleton). Bodies are grouped by bulk index into thirds
    (:func:`bulk_groups`; ``body_groups`` overrides: name -> group); a clip is a contact clip when at least
    ``contact_fraction`` of its frames have a hand self-contact on the source body. Writes ``eval.json`` and
    ``eval.md`` into ``out_dir`` when given. ``threads``: torch threads during the run (see
    :data:`MEASURE_THREADS`)."""
    with torch_threads(threads):
        return _run_evaluation(
            motions, bodies, methods, out_dir, max_frames, fps, contact_fraction, body_groups, log, source_character
        )


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
    source_character: str | Path | None,
) -> EvalTable:
    from retarget_core.pipeline import prepare, refine

    started = time.perf_counter()
    methods = list(methods or ["copy"])
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; available: {sorted(METHODS)}")
    order = ["copy"] + [m for m in methods if m != "copy"]
    say = log or (lambda _m: None)

    infos: list[BodyInfo] = []
    for b in bodies:
        tc = load_character(b).character
        infos.append(BodyInfo(name=tc.name, height_m=round(tc.height, 4), bulk_index=round(bulk_index(tc), 5), group=""))
    for info, group in zip(infos, bulk_groups([i.bulk_index for i in infos]), strict=True):
        info.group = (body_groups or {}).get(info.name) or group

    rows: list[EvalRow] = []
    clips: list[ClipInfo] = []
    for path in motions:
        clip_info: ClipInfo | None = None
        for b, info in zip(bodies, infos, strict=True):
            t = time.perf_counter()
            inputs = JobInputs(path, b, source_character, method_options("copy", fps))
            prepared = prepare(inputs, max_frames=max_frames)
            found = prepared.contacts
            if clip_info is None:
                motion = prepared.source.motion
                contact_frames = int(found.self_contacts.frames_with_contact().sum())
                enough = contact_frames >= contact_fraction * motion.num_frames and contact_frames > 0
                pairs = [{k: e[k] for k in ("hand", "other", "frames")} for e in found.self_contacts.summary()[:6]]
                clip_info = ClipInfo(name=motion.name, frames=motion.num_frames, fps=motion.fps,
                                     contact_frames=contact_frames, group="contact" if enough else "no-contact",
                                     contacts=pairs)  # fmt: skip
                clips.append(clip_info)
                say(f"{motion.name}: {motion.num_frames} frames, {contact_frames} with hand contacts ({clip_info.group})")
            for m in order:
                after = None if m == "copy" else refine(prepared, options=method_options(m, fps)).after
                p = prepared
                job = measure_job(
                    p.source_body.character, p.source_body.mapping, p.source_view, p.target.character,
                    p.target.mapping, p.before, after, source_contacts=found, constraints=p.constraints,
                    include_series=False, threads=None,
                )  # fmt: skip
                rows.append(EvalRow(method=m, body=info.name, clip=clip_info.name, values=_summary_values(job.report, m)))
            v = rows[-1].values
            say(
                f"  {info.name:>20}: {order[-1]} pen. verts {_fmt(v['penetrating_vertices_percent'])} %, "
                f"max {_fmt(v['penetration_max_depth'])} cm ({time.perf_counter() - t:.1f}s)"
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
        settings={"max_frames": max_frames, "fps": fps, "contact_fraction": contact_fraction,
                  "methods": {m: list(METHODS[m]) for m in order}},
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
    "method_options",
    "run_evaluation",
    "write_eval_table",
]
