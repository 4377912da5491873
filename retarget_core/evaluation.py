"""The evaluation table (``retarget eval``): methods x motions x bodies, with the acceptance figures of
``../shared/ACCEPTANCE.md`` (:mod:`retarget_core.metrics.acceptance`) and our own metrics, by body group and
contact / no-contact clip, with the ratios to the copy where the targets are ratios.

A method is a set of refinement stages (:data:`METHODS`): ``copy`` runs none (the baseline, always measured
first: the ratios, MPJPE and M_i / M_o of every other method are against it). Every job runs through
:func:`retarget_core.pipeline.prepare` and :func:`retarget_core.pipeline.refine`, exactly as a job of the
service or the CLI does. The acceptance figures are measured like the judge does: the result on the target
against the source motion on its own body (the source view; with ``source_glb_body`` the clip is first written
as a GLB on that body and read back, as a studio would send it).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, Field

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.jobs import JobInputs
from retarget_core.loading import load_character
from retarget_core.measure import MEASURE_THREADS, measure_job, torch_threads
from retarget_core.metrics.acceptance import (
    AcceptanceFigures,
    ClipAcceptance,
    figures_from_measures,
    load_judged_file,
    measure_acceptance,
    meets_targets,
)
from retarget_core.metrics.report import MetricsReport
from retarget_core.model.inference import network_weights
from retarget_core.motion import Motion
from retarget_core.options import RetargetOptions
from retarget_core.stages import REFINEMENT_STAGE_NAMES, stage_info

METHODS: dict[str, tuple[str, ...]] = {
    "copy": (),
    "collisions": ("collisions",),
    "foot_lock": ("foot_lock",),
    "collisions+foot_lock": ("collisions", "foot_lock"),
    "learned_collisions": ("learned_collisions",),
    "learned_collisions+collisions": ("learned_collisions", "collisions"),
    "learned_collisions+collisions+foot_lock": ("learned_collisions", "collisions", "foot_lock"),
    "recurrent+eso": ("recurrent", "eso"),
    "recurrent+eso+collisions+foot_lock": ("recurrent", "eso", "collisions", "foot_lock"),
    "full": tuple(n for n in REFINEMENT_STAGE_NAMES if stage_info(n).available and stage_info(n).default),
}
"""Method name -> the refinement stages it runs (``full``: the default chain, what a job runs unless told)."""

MODELS_DIR = Path(__file__).resolve().parent / "data" / "models"
ABLATED_ENERGIES: tuple[str, ...] = ("skeleton", "foot", "interpenetration")
METHODS.update({"recurrent": ("recurrent",), **{f"recurrent[{e}]": ("recurrent",) for e in ABLATED_ENERGIES}})
METHOD_WEIGHTS: dict[str, Path] = {f"recurrent[{e}]": MODELS_DIR / f"recurrent-{e}.pt" for e in ABLATED_ENERGIES}
"""Methods that run the network with other weights than the shipped ones (``retarget train recurrent --energy
E -o retarget_core/data/models/recurrent-E.pt``; ``recurrent[pointnet]``: ``--geometry pointnet -o
retarget_core/data/models/recurrent-pointnet.pt``, the PointNet geometry code, docs/model-recurrent.md)."""
METHODS["recurrent[pointnet]"] = ("recurrent",)
METHOD_WEIGHTS["recurrent[pointnet]"] = MODELS_DIR / "recurrent-pointnet.pt"
METHODS["full[eso12]"] = METHODS["full"]
METHODS["full[no-network]"] = tuple(n for n in METHODS["full"] if n not in ("recurrent", "eso"))
METHODS["full[no-eso]"] = tuple(n for n in METHODS["full"] if n != "eso")  # the network's output unoptimised
METHOD_SETTINGS: dict[str, dict[str, int]] = {"full[eso12]": {"eso_iterations": 12}}
"""Methods that run their stages with other job options than the defaults (``full[eso12]``: the default chain
with 12 ESO steps instead of 30, the speed/quality comparison in docs/model-recurrent.md)."""
ABLATION: tuple[str, ...] = (
    "copy", "recurrent[skeleton]", "recurrent[foot]", "recurrent[interpenetration]", "recurrent", "recurrent+eso",
    "recurrent+eso+collisions+foot_lock", "collisions+foot_lock",
)  # fmt: skip
"""Paper 1 table 3's rows: copy; the network trained on skeleton terms only, + foot, + interpenetration, the full
energy (the shipped weights); + ESO; + collisions and foot lock; and collisions + foot lock without the network."""


def method_options(method: str, fps: float | None) -> RetargetOptions:
    """The job options of ``method``: its refinement stages on, the others off, contacts on."""
    stages = {n: n in METHODS[method] for n in REFINEMENT_STAGE_NAMES}
    return RetargetOptions(fps=fps, stages={"contacts": True, **stages}, **METHOD_SETTINGS.get(method, {}))


# --- what is tabled ------------------------------------------------------------------------------------------

ACCEPTANCE_METRICS: tuple[tuple[str, str], ...] = (
    ("pen_percent", "pen %v"),
    ("frames_over_1cm_percent", "frames >1cm %"),
    ("head_percent", "head %v"),
    ("contact_preservation", "contact pres."),
    ("false_contacts", "false contacts"),
    ("foot_accuracy", "foot acc."),
    ("skate_cm", "skate cm/fr"),
    ("ground_penetration_cm", "ground pen. cm"),
    ("float_cm", "float cm"),
    ("end_effector_error_cm", "EE err cm"),
    ("jerk_ratio", "jerk ratio"),
)
"""The judge's figures (ACCEPTANCE.md), at 1.80 m and 30 fps."""

OUR_METRICS: tuple[tuple[str, str], ...] = (
    ("penetrating_vertices_percent", "SDF pen. %v"),
    ("penetration_max_depth", "pen. max cm"),
    ("m_c", "M_c cm^2"),
    ("m_i", "M_i cm^2"),
    ("m_o", "M_o cm^2"),
    ("contact_distance_mean", "pair dist. cm"),
    ("mpjpe", "MPJPE cm"),
)
"""Our own measures (docs/metrics.md), at 1.80 m; M_i / M_o and MPJPE are against the copy."""

RATIO_METRICS: tuple[str, ...] = ("pen_percent", "frames_over_1cm_percent", "end_effector_error_cm", "head_percent")
"""Figures whose targets are ratios to the copy: tabled as after / before of the group means."""
WORST_CASE: dict[str, str] = {"contact_preservation": "min", "foot_accuracy": "min", "false_contacts": "max"}
"""Figures whose targets hold on every clip x body: the group's worst job is tabled beside the mean."""


class BodyInfo(BaseModel):
    name: str
    height_m: float
    bulk_index: float = Field(description="mesh volume / height^3 (higher is bulkier)")
    group: str = Field(description="body group: given (held-out split) or skinny / medium / bulky by bulk")


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
    values: dict[str, float | None] = Field(description="acceptance figures and our metrics at 1.80 m")
    targets_met: dict[str, bool] = Field(default_factory=dict, description="ACCEPTANCE.md targets vs the copy")
    ms_per_frame: float | None = Field(default=None, description="refinement stages' time per frame (copy: 0)")


class EvalGroup(BaseModel):
    method: str
    bodies: str
    clips: str
    jobs: int
    values: dict[str, float | None] = Field(description="means over the jobs of the group (nulls left out)")
    worst: dict[str, float | None] = Field(default_factory=dict, description="see WORST_CASE")
    ratios: dict[str, float | None] = Field(default_factory=dict, description="group mean / the copy's")
    targets_met_share: float | None = Field(default=None, description="share of jobs meeting every target")
    ms_per_frame: float | None = None


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
        """The grouped tables as Markdown (lengths at a 1.80 m character)."""
        acc = [n for n, _ in ACCEPTANCE_METRICS]
        ours = [n for n, _ in OUR_METRICS]
        out = ["## Acceptance figures by body group and clip group", ""]
        out += _group_table(self.groups, acc, self.labels, with_targets=True)
        out += ["", "## Ratios to the copy (targets: pen %v <= 0.25, frames >1cm <= 0.2, EE err <= 1.3)", ""]
        out += ["| method | bodies | clips | jobs | " + " | ".join(self.labels[r] for r in RATIO_METRICS) + " |"]
        out += ["|" + "---|" * (4 + len(RATIO_METRICS))]
        out += [f"| {g.method} | {g.bodies} | {g.clips} | {g.jobs} | " + " | ".join(_fmt(g.ratios.get(r)) for r in RATIO_METRICS) + " |"
                for g in self.groups if g.method != "copy"]  # fmt: skip
        out += ["", "## Our metrics (SDF penetration, paper 2's M_c / M_i / M_o, MPJPE vs the copy)", ""]
        out += _group_table(self.groups, ours, self.labels, with_targets=False)
        out += ["", "## By body, all clips", ""]
        out += _group_table(self.per_body, acc, self.labels, with_targets=True)
        if self.settings.get("per_case"):
            out += ["", "## Every case (ratios to the copy of the same case)", ""] + case_table(self.rows, self.methods)
        out += ["", "## Bodies", "", "| body | height m | bulk index | group |", "|---|---|---|---|"]
        out += [f"| {b.name} | {b.height_m:.3f} | {b.bulk_index:.4f} | {b.group} |" for b in self.bodies]
        out += ["", "## Clips", "", "| clip | frames | fps | contact frames | group | main contacts (frames) |",
                "|---|---|---|---|---|---|"]  # fmt: skip
        out += [
            f"| {c.name} | {c.frames} | {c.fps:g} | {c.contact_frames} | {c.group} | "
            + ", ".join(f"{e['hand']}-{e['other']} ({e['frames']})" for e in c.contacts[:3])
            + " |"
            for c in self.clips
        ]
        return "\n".join(out) + "\n"


CASE_COLUMNS: tuple[tuple[str, str, bool], ...] = (
    ("pen_percent", "pen %v x", True), ("frames_over_1cm_percent", ">1cm x", True), ("head_percent", "head x", True),
    ("end_effector_error_cm", "EE x", True), ("contact_preservation", "contact pres.", False),
    ("false_contacts", "false contacts", False), ("jerk_ratio", "jerk", False), ("float_cm", "float cm", False),
)  # fmt: skip
"""The per-case table's columns: (figure, label, tabled as a ratio to the same case's copy)."""


def case_table(rows: list[EvalRow], methods: list[str]) -> list[str]:
    """One line per case and method other than the copy: the targets' figures, whether every target is met and
    which are missed."""
    copy = {(r.clip, r.body): r for r in rows if r.method == "copy"}
    head = "| method | clip | body | " + " | ".join(label for _, label, _ in CASE_COLUMNS) + " | all met | missed |"
    lines = [head, "|" + "---|" * (5 + len(CASE_COLUMNS))]
    for r in rows:
        if r.method == "copy" or r.method not in methods:
            continue
        base = copy.get((r.clip, r.body))
        cells = [_fmt(_case_value(r, base, name, ratio)) for name, _, ratio in CASE_COLUMNS]
        missed = ", ".join(k for k, ok in r.targets_met.items() if not ok)
        met = "yes" if r.targets_met and all(r.targets_met.values()) else "no"
        lines.append(f"| {r.method} | {r.clip} | {r.body} | " + " | ".join(cells) + f" | {met} | {missed} |")
    return lines


def _case_value(row: EvalRow, copy: EvalRow | None, name: str, ratio: bool) -> float | None:
    value = row.values.get(name)
    if not ratio:
        return value
    base = copy.values.get(name) if copy is not None else None
    return round(value / base, 4) if value is not None and base else None


def _group_table(groups: list[EvalGroup], cols: list[str], labels: dict[str, str], with_targets: bool) -> list[str]:
    extra = ["worst", "all targets met", "ms/frame"] if with_targets else []
    head = "| method | bodies | clips | jobs | " + " | ".join([labels[c] for c in cols] + extra) + " |"
    lines = [head, "|" + "---|" * (4 + len(cols) + len(extra))]
    for g in groups:
        cells = [_fmt(g.values.get(c)) for c in cols]
        if with_targets:
            worst = ", ".join(f"{labels[k]} {_fmt(v)}" for k, v in g.worst.items())
            met = "-" if g.targets_met_share is None else f"{100 * g.targets_met_share:.0f} %"
            cells += [worst, met, _fmt(g.ms_per_frame)]
        lines.append(f"| {g.method} | {g.bodies} | {g.clips} | {g.jobs} | " + " | ".join(cells) + " |")
    return lines


def _fmt(v: float | None) -> str:
    if v is None:
        return "-"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"


def _our_values(report: MetricsReport, method: str) -> dict[str, float | None]:
    metrics = report.before if method == "copy" else report.after
    assert metrics is not None
    out: dict[str, float | None] = {}
    for name, _ in OUR_METRICS:
        v = getattr(metrics.summary, name)
        out[name] = v.value_at_180 if hasattr(v, "value_at_180") else v
    return out


def _acceptance_values(fig: AcceptanceFigures) -> dict[str, float | None]:
    return {name: getattr(fig, name) for name, _ in ACCEPTANCE_METRICS}


def _mean(vals: list[float | None]) -> float | None:
    xs = [v for v in vals if v is not None]
    return round(sum(xs) / len(xs), 4) if xs else None


def _summarise(method: str, bodies: str, clips: str, sel: list[EvalRow], copy: list[EvalRow]) -> EvalGroup:
    names = list(sel[0].values)
    values = {n: _mean([r.values.get(n) for r in sel]) for n in names}
    worst: dict[str, float | None] = {}
    for n, how in WORST_CASE.items():
        xs = [v for r in sel if (v := r.values.get(n)) is not None]
        worst[n] = (min(xs) if how == "min" else max(xs)) if xs else None
    ratios: dict[str, float | None] = {}
    for n in RATIO_METRICS:
        a, b = values.get(n), _mean([r.values.get(n) for r in copy])
        ratios[n] = round(a / b, 4) if a is not None and b else None
    met = [all(r.targets_met.values()) for r in sel if r.targets_met]
    times = [r.ms_per_frame for r in sel]
    return EvalGroup(method=method, bodies=bodies, clips=clips, jobs=len(sel), values=values, worst=worst,
                     ratios=ratios, targets_met_share=(sum(met) / len(met)) if met else None,
                     ms_per_frame=_mean(times))  # fmt: skip


def group_rows(rows: list[EvalRow], methods: list[str], body_group: dict[str, str], clip_group: dict[str, str],
               body_order: list[str]) -> tuple[list[EvalGroup], list[EvalGroup]]:  # fmt: skip
    """The table's groups: (method x body group x clip group, "all" included) and (method x body)."""
    groups: list[EvalGroup] = []
    bgs = sorted(set(body_group.values())) + ["all"]
    for m in methods:
        for bg in bgs:
            for cg in ("contact", "no-contact", "all"):
                def keep(r: EvalRow, bg: str = bg, cg: str = cg) -> bool:
                    return bg in ("all", body_group[r.body]) and cg in ("all", clip_group[r.clip])

                sel = [r for r in rows if r.method == m and keep(r)]
                if sel:
                    copy = [r for r in rows if r.method == "copy" and keep(r)]
                    groups.append(_summarise(m, bg, cg, sel, copy))
    per_body = [
        _summarise(m, b, "all", sel, [r for r in rows if r.method == "copy" and r.body == b])
        for m in methods
        for b in body_order
        if (sel := [r for r in rows if r.method == m and r.body == b])
    ]
    return groups, per_body


# --- bodies --------------------------------------------------------------------------------------------------


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


# --- the run -------------------------------------------------------------------------------------------------


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
    source_glb_body: str | Path | None = None,
    jobs: int = 1,
    cases: list[tuple[Path, str | Path]] | None = None,
) -> EvalTable:
    """Run ``methods`` (default: copy) on every motion x body, or on the fixed ``cases`` (motion, body), and
    summarise.

    motions: BVH/glTF/FBX files; bodies: character files or ``builtin:<preset>``; ``max_frames``: first frames
    of each clip (after resampling to ``fps``; None: all); ``source_character``: the body performing the source
    motions (default: the motion file's own mesh, or a built-in body sized to the source skeleton);
    ``source_glb_body``: first write each clip as a GLB on this body and use that as the motion (what a studio
    sends; the judge's setting). Bodies are grouped by ``body_groups`` (name -> group) or by bulk index into
    thirds (:func:`bulk_groups`); a clip is a contact clip when at least ``contact_fraction`` of its frames
    have a hand self-contact on the source body. Writes ``eval.json`` and ``eval.md`` into ``out_dir`` when
    given. ``threads``: torch threads during the run (see :data:`MEASURE_THREADS`); ``jobs``: clips evaluated in
    parallel worker processes (one torch thread each). With ``cases`` (``motions`` and ``bodies`` then empty)
    only those pairs run, each clip once on its bodies, and ``eval.md`` also tables every case."""
    methods = list(methods or ["copy"])
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; available: {sorted(METHODS)}")
    missing = [f"{m} ({METHOD_WEIGHTS[m]})" for m in methods if m in METHOD_WEIGHTS and not METHOD_WEIGHTS[m].is_file()]
    if missing:
        raise ValueError(f"no weights for {', '.join(missing)}: train them with retarget train recurrent --energy ...")
    if cases is not None and (motions or bodies):
        raise ValueError("give either motions and bodies or a case list, not both")
    plan = group_cases(cases) if cases is not None else [(m, list(bodies)) for m in motions]
    with torch_threads(threads):
        return _run_evaluation(plan, methods, out_dir, max_frames, fps, contact_fraction, body_groups,
                               log, source_character, source_glb_body, jobs, per_case=cases is not None)  # fmt: skip


def group_cases(cases: list[tuple[Path, str | Path]]) -> list[tuple[Path, list[str | Path]]]:
    """A case list as (clip, its bodies), clips in order of first appearance; a repeated case raises."""
    plan: dict[Path, list[str | Path]] = {}
    for motion, body in cases:
        bodies = plan.setdefault(Path(motion), [])
        if body in bodies:
            raise ValueError(f"case {Path(motion).name} on {body} is listed twice")
        bodies.append(body)
    return list(plan.items())


def source_as_glb(motion: Path, body: str | Path, out: Path, max_frames: int | None, fps: float | None) -> Path:
    """``motion`` performed by ``body`` (copy retargeting, placed on the floor by its mesh where the clip's feet
    are planted, as a studio's file stands on its floor), written as an animated GLB at ``out``."""
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.io.gltf_write import write_glb
    from retarget_core.pipeline import prepare_source
    from retarget_core.placement import stand_on_own_feet

    src = prepare_source(JobInputs(motion, body, options=RetargetOptions(fps=fps)), max_frames)
    tgt = load_character(body)
    ch, mapping = tgt.character, tgt.mapping
    view = stand_on_own_feet(ch, mapping, copy_retarget(src.motion, src.mapping, ch.skeleton, mapping))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_glb(ch, view, out, clip_name=Path(motion).stem)  # the file's name, as the table names the clip
    return out


def _body_infos(bodies: list[str | Path], body_groups: dict[str, str] | None) -> list[BodyInfo]:
    """Name, height, bulk index and group of each body (groups: ``body_groups`` or thirds of bulk)."""
    infos: list[BodyInfo] = []
    for b in bodies:
        tc = load_character(b).character
        info = BodyInfo(name=tc.name, height_m=round(tc.height, 4), bulk_index=round(bulk_index(tc), 5), group="")
        infos.append(info)
    for info, group in zip(infos, bulk_groups([i.bulk_index for i in infos]), strict=True):
        info.group = (body_groups or {}).get(info.name) or group
    return infos


ClipTask = tuple[Path, list[str | Path], list[str], list[str], int | None, float | None, float, str | Path | None]
"""The arguments of :func:`_evaluate_clip` for one clip: its file, its bodies and their names, the methods, the
frames, the rate, the contact fraction and the source character."""


def _run_tasks(tasks: list[ClipTask], jobs: int, say: Callable[[str], None]) -> list[tuple[ClipInfo, list[EvalRow], list[str]]]:  # fmt: skip
    """:func:`_evaluate_clip` on every task, in ``jobs`` worker processes when more than one."""
    if jobs > 1 and len(tasks) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
            results = list(pool.map(_evaluate_clip_in_worker, tasks))
        for _info, _rows, lines in results:
            for line in lines:
                say(line)
        return results
    return [_evaluate_clip(*t, log=say) for t in tasks]


def _run_evaluation(
    plan: list[tuple[Path, list[str | Path]]],
    methods: list[str],
    out_dir: Path | None,
    max_frames: int | None,
    fps: float | None,
    contact_fraction: float,
    body_groups: dict[str, str] | None,
    log: Callable[[str], None] | None,
    source_character: str | Path | None,
    source_glb_body: str | Path | None,
    jobs: int,
    per_case: bool = False,
) -> EvalTable:
    import tempfile

    started = time.perf_counter()
    order = ["copy"] + [m for m in methods if m != "copy"]
    say = log or (lambda _m: None)
    bodies = list(dict.fromkeys(b for _, clip_bodies in plan for b in clip_bodies))
    infos = _body_infos(bodies, body_groups)
    name_of = {b: i.name for b, i in zip(bodies, infos, strict=True)}

    rows: list[EvalRow] = []
    clips: list[ClipInfo] = []
    scratch = tempfile.TemporaryDirectory(prefix="retarget-eval-")
    tasks: list[ClipTask] = []
    for path, clip_bodies in plan:
        if source_glb_body is not None:
            path = source_as_glb(path, source_glb_body, Path(scratch.name) / f"{path.stem}.glb", max_frames, fps)
        names = [name_of[b] for b in clip_bodies]
        tasks.append((path, clip_bodies, names, order, max_frames, fps, contact_fraction, source_character))
    for clip_info, clip_rows, _lines in _run_tasks(tasks, jobs, say):
        clips.append(clip_info)
        rows += clip_rows
    scratch.cleanup()

    body_group = {i.name: i.group for i in infos}
    clip_group = {c.name: c.group for c in clips}
    body_order = [i.name for i in sorted(infos, key=lambda x: x.bulk_index)]
    groups, per_body = group_rows(rows, order, body_group, clip_group, body_order)
    table = EvalTable(
        methods=order,
        metrics=[n for n, _ in ACCEPTANCE_METRICS + OUR_METRICS],
        labels=dict(ACCEPTANCE_METRICS + OUR_METRICS),
        bodies=sorted(infos, key=lambda x: x.bulk_index),
        clips=clips,
        rows=rows,
        groups=groups,
        per_body=per_body,
        seconds=round(time.perf_counter() - started, 2),
        settings={"max_frames": max_frames, "fps": fps, "contact_fraction": contact_fraction,
                  "source_glb_body": str(source_glb_body) if source_glb_body else None, "jobs": jobs,
                  "methods": {m: list(METHODS[m]) for m in order}, "per_case": per_case,
                  "cases": len(rows) // len(order)},  # fmt: skip
    )
    say(table.to_markdown())
    if out_dir is not None:
        write_eval_table(table, out_dir)
    return table


def _evaluate_clip(
    path: Path, bodies: list[str | Path], body_names: list[str], order: list[str], max_frames: int | None,
    fps: float | None, contact_fraction: float, source_character: str | Path | None,
    log: Callable[[str], None] | None = None,
) -> tuple[ClipInfo, list[EvalRow], list[str]]:
    """Every method on one clip x every body: the clip's info, the rows and the log lines."""
    from retarget_core.pipeline import prepare, refine

    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        if log is not None:
            log(line)

    rows: list[EvalRow] = []
    clip_info: ClipInfo | None = None
    src_acc: ClipAcceptance | None = None
    for b, body_name in zip(bodies, body_names, strict=True):
        t = time.perf_counter()
        prepared = prepare(JobInputs(path, b, source_character, method_options("copy", fps)), max_frames=max_frames)
        p, tgt = prepared, prepared.target
        if clip_info is None or src_acc is None:
            clip_info = _clip_info(prepared, contact_fraction)
            src_acc = _source_acceptance(path, prepared)
            say(f"{clip_info.name}: {clip_info.frames} frames, {clip_info.contact_frames} with hand contacts "
                f"({clip_info.group})")  # fmt: skip
        copy_fig: AcceptanceFigures | None = None
        for m in order:
            t_m = time.perf_counter()
            with network_weights(METHOD_WEIGHTS.get(m)):
                after = None if m == "copy" else refine(prepared, options=method_options(m, fps)).after
            ms = 0.0 if after is None else 1000 * (time.perf_counter() - t_m) / prepared.before.num_frames
            fig = figures_from_measures(measure_acceptance(tgt.character, tgt.mapping, p.before if after is None else after), src_acc)
            job = measure_job(
                p.source_body.character, p.source_body.mapping, p.source_view, tgt.character, tgt.mapping,
                p.before, after, source_contacts=p.contacts, constraints=p.constraints, include_series=False,
                threads=None, measure_source_motion=False,
            )  # fmt: skip
            copy_fig = copy_fig or fig
            met = {k: c.met for k, c in meets_targets(fig, copy_fig).items()}
            rows.append(EvalRow(method=m, body=body_name, clip=clip_info.name,
                                values={**_acceptance_values(fig), **_our_values(job.report, m)},
                                targets_met=met, ms_per_frame=round(ms, 3)))  # fmt: skip
        v = rows[-1].values
        say(f"  {body_name:>20}: {order[-1]} pen %v {_fmt(v['pen_percent'])}, contact pres. "
            f"{_fmt(v['contact_preservation'])}, foot acc. {_fmt(v['foot_accuracy'])} ({time.perf_counter() - t:.1f}s)")
    assert clip_info is not None
    return clip_info, rows, lines


def judged_source(path: Path, prepared: Any) -> tuple[Character, JointMapping, Motion] | None:
    """A GLB source with its own body as the judge reads the file (its own floor, no re-grounding), its clip
    resampled and cut as ``prepared``'s source view; None when ``path`` is not such a file."""
    if path.suffix.lower() not in (".glb", ".gltf"):
        return None
    try:
        character, mapping, motion = load_judged_file(path)
    except ValueError:
        return None
    from retarget_core.resample import resample

    return character, mapping, resample(motion, prepared.source_view.fps).slice(0, prepared.source_view.num_frames)


def _source_acceptance(path: Path, prepared: Any) -> ClipAcceptance:
    """The judge's measures of the source: :func:`judged_source` when the file has its own body; otherwise the
    source motion on the body the pipeline gave it."""
    judged = judged_source(path, prepared)
    if judged is not None:
        return measure_acceptance(*judged)
    p = prepared
    return measure_acceptance(p.source_body.character, p.source_body.mapping, p.source_view)


def _evaluate_clip_in_worker(task: tuple[Any, ...]) -> tuple[ClipInfo, list[EvalRow], list[str]]:
    """:func:`_evaluate_clip` in a worker process (one torch thread: the processes share the cores)."""
    torch.set_num_threads(1)
    return _evaluate_clip(*task)


def _clip_info(prepared: Any, contact_fraction: float) -> ClipInfo:
    motion = prepared.source.motion
    sc = prepared.contacts.self_contacts
    contact_frames = int(sc.frames_with_contact().sum())
    enough = contact_frames >= contact_fraction * motion.num_frames and contact_frames > 0
    pairs = [{k: e[k] for k in ("hand", "other", "frames")} for e in sc.summary()[:6]]
    return ClipInfo(name=motion.name, frames=motion.num_frames, fps=motion.fps, contact_frames=contact_frames,
                    group="contact" if enough else "no-contact", contacts=pairs)  # fmt: skip


def write_eval_table(table: EvalTable, out_dir: Path) -> tuple[Path, Path]:
    """``eval.json`` and ``eval.md`` in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    js, md = out_dir / "eval.json", out_dir / "eval.md"
    js.write_text(json.dumps(table.model_dump(mode="json"), indent=1))
    md.write_text(f"# Evaluation\n\n{table.seconds:.0f} s in all.\n\n" + table.to_markdown())
    return js, md


__all__ = [
    "ACCEPTANCE_METRICS",
    "METHODS",
    "OUR_METRICS",
    "EvalTable",
    "bulk_groups",
    "bulk_index",
    "case_table",
    "group_cases",
    "group_rows",
    "judged_source",
    "method_options",
    "run_evaluation",
    "source_as_glb",
    "write_eval_table",
]
