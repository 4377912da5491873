"""Time every stage of contact detection, correspondence, SDF precomputation, metrics and energies.

Defaults: a 300-frame piece (at 30 fps) of CMU 02_08 (swordplay, two-hand grips) on the bulky shared body
(13,380 vertices), the source on the built-in body sized to the clip. Prints a table and writes JSON.

    python benchmarks/bench/metrics_benchmark.py [--motion CLIP] [--target BODY] [--frames 300] [-o out.json]

``--job``: the job's metrics stage instead (``measure_job`` as ``metrics_summary.build_metrics`` calls it, after
a default-chain refinement of the same clip): the default path against ``every_frame=True`` (every frame and
every hand-to-part distance measured exactly, the path before issue 20), timed, in ms per frame, and their
reports compared (timings apart); writes ``metrics_job_benchmark.json``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    add_clip_options,
    add_output,
    character_path,
    machine,
    parser,
    results_dir,
    source_frames,
    timer,
    write_json,
)

PER_JOB_EXCLUDED = ("read", "part SDF", "E_int", "penetration query")
"""Steps a job does not pay each time: file reads, the per-body SDF (cached) and the energy timings."""


class Steps:
    """Wall and CPU seconds of each named step, printed as they come."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def run(self, name: str, fn: Callable[[], Any]) -> Any:
        with timer() as t:
            out = fn()
        self.wall[name], self.cpu[name] = round(t.wall_s, 3), round(t.cpu_s, 3)
        print(f"  {name:<40} {self.wall[name]:8.3f} s wall {self.cpu[name]:8.3f} s cpu", flush=True)
        return out


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--target", default=str(character_path("mh_male_bulky")), help="the target body")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's own choice)")
    add_output(ap, results_dir("bench") / "metrics_benchmark.json")
    ap.add_argument("--job", action="store_true", help="time the job's metrics stage, default vs every frame")
    ap.add_argument("--repeats", type=int, default=2, help="--job: timed runs of each path (the best is kept)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.job:
        job_metrics(args)
        return
    print(f"benchmark: {args.motion.name} on {Path(args.target).name}, {args.frames} frames at {args.fps} fps")
    steps = Steps()
    out = measure_steps(args, steps)
    steps.run("E_int + E_j2j forward+backward", out.pop("energies"))
    steps.run("penetration query, one frame", out.pop("one_frame_query"))
    out["seconds"], out["cpu_seconds"] = steps.wall, steps.cpu
    out["per_job_seconds_excluding_reads_and_sdf"] = round(
        sum(v for k, v in steps.wall.items() if not k.startswith(PER_JOB_EXCLUDED)), 3)  # fmt: skip
    out["machine"] = {**machine(), "torch_threads": torch.get_num_threads()}
    print(f"per job (contacts, correspondence, metrics; no file reads, SDF cached): {out['per_job_seconds_excluding_reads_and_sdf']} s")
    write_json(args.output, out)


def measure_steps(args: argparse.Namespace, steps: Steps) -> dict[str, Any]:
    """Read to metrics JSON, each step timed; the figures, and the two energy timings still to run
    (``energies``, ``one_frame_query``: callables)."""
    from retarget_core.body_parts import body_parts
    from retarget_core.contacts.correspondence import build_correspondence, transfer_contacts
    from retarget_core.contacts.foot_contact import detect_foot_contacts
    from retarget_core.contacts.self_contact import detect_self_contacts
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.energy.sdf import build_part_sdf
    from retarget_core.loading import load_character, load_motion
    from retarget_core.measure import SourceContactResult, source_contacts_model
    from retarget_core.metrics.compute import measure_clip, summarize
    from retarget_core.metrics.report import build_metrics_report, write_metrics_json
    from retarget_core.resample import resample
    from retarget_core.source_body import source_body_for

    run = steps.run
    src = run("read motion", lambda: load_motion(args.motion))
    src.motion = resample(src.motion, args.fps).slice(0, args.frames)
    tgt = run("read target", lambda: load_character(args.target))
    body, body_map = run("source body (built-in, sized)", lambda: source_body_for(src.motion.skeleton, src.mapping))
    view = run("copy onto source body", lambda: copy_retarget(src.motion, src.mapping, body.skeleton, body_map))
    before = run("copy onto target", lambda: copy_retarget(src.motion, src.mapping, tgt.character.skeleton, tgt.mapping))
    grot, gpos = view.global_transforms()
    with torch.no_grad():
        posed = run("skin source body (LBS)", lambda: body.pose_vertices(grot, gpos))
    parts = body_parts(body, body_map)
    sc = run("hand self-contacts (source)", lambda: detect_self_contacts(parts, posed, body.height, view.fps))
    _, rest = body.skeleton.rest_global()
    feet = run("foot contacts (source)", lambda: detect_foot_contacts(gpos, rest, body_map, body.height, view.fps))
    corr = run("correspondence features + KD-tree", lambda: build_correspondence(body, body_map, tgt.character, tgt.mapping))
    cons = run("transfer contacts", lambda: transfer_contacts(sc, corr))
    tparts = body_parts(tgt.character, tgt.mapping)
    sdf = run("part SDF grids (target, once per body)", lambda: build_part_sdf(tgt.character, tparts))
    measures = run("measure before (pose + SDF queries)", lambda: measure_clip(tgt.character, tgt.mapping, sdf, before, cons))
    metrics = run("summarise metrics", lambda: summarize(measures, source_feet=feet))
    report = build_metrics_report(
        before.name, tgt.character.name, tgt.character.height, metrics,
        source_contacts=source_contacts_model(SourceContactResult(sc, feet, body.name), cons),
        timings_s={k: v for k, v in steps.wall.items() if k in ("hand self-contacts (source)", "measure before (pose + SDF queries)")},
    )  # fmt: skip
    run("write metrics JSON", lambda: write_metrics_json(report, args.output.with_name("metrics_benchmark_report.json")))
    energies, one_frame = energy_timings(tgt.character, tparts, sdf, before, cons)
    return {
        "motion": args.motion.name, "target": tgt.character.name, "frames": view.num_frames, "fps": view.fps,
        "target_vertices": tgt.character.num_vertices, "target_triangles": int(tgt.character.faces.shape[0]),
        "source_contacts": sc.count, "constraints": cons.count,
        "penetration_volume_cm3_at_180": metrics.summary.penetration_volume.value_at_180,
        "energies": energies, "one_frame_query": one_frame,
    }  # fmt: skip


def energy_timings(character: Any, parts: Any, sdf: Any, before: Any, cons: Any) -> tuple[Callable[[], float], Callable[[], Any]]:
    """Two steps to time: E_int and E_j2j on every frame, forward and backward through skinning; and the
    penetration query of one frame."""
    from retarget_core.energy.sdf import sample_pairs, segment_matrices, vertex_depths
    from retarget_core.energy.terms import interpenetration_energy, vertex_contact_energy

    tr, tp = before.global_transforms()
    tp = tp.clone().requires_grad_(True)

    def energies() -> float:
        verts = character.pose_vertices(tr, tp)
        mats = segment_matrices(character, parts, tr, tp)
        e = interpenetration_energy(sdf, verts, mats) + vertex_contact_energy(verts, cons, character.height)
        e.sum().backward()
        return float(e.detach().sum())

    with torch.no_grad():
        v1 = character.pose_vertices(tr[:1], tp[:1].detach())
        m1 = segment_matrices(character, parts, tr[:1], tp[:1].detach())

    def one_frame() -> Any:
        with torch.no_grad():
            return vertex_depths(sdf, sample_pairs(sdf, v1, m1), 1)

    return energies, one_frame


def _numbers_differ(a: Any, b: Any, path: str = "") -> list[str]:
    """Paths where two JSON values differ beyond float noise (relative 1e-3, absolute 2e-4)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in _numbers_differ(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _numbers_differ(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, int | float):
        return [] if math.isclose(a, b, rel_tol=1e-3, abs_tol=2e-4) else [f"{path}: {a} vs {b}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def job_metrics(args: argparse.Namespace) -> None:
    """``--job``: see the module doc."""
    from retarget_core.body_cache import body_assets
    from retarget_core.jobs import JobInputs
    from retarget_core.measure import measure_job, torch_threads
    from retarget_core.metrics_summary import job_context
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import PIPELINE_THREADS, prepare, refine

    opts = RetargetOptions(fps=args.fps, frame_end=source_frames(args.motion, args.frames, args.fps))
    print(f"metrics stage: {args.motion.name} on {Path(args.target).name}, {args.frames} frames, default chain")
    with torch_threads(PIPELINE_THREADS):
        result = refine(prepare(JobInputs(args.motion, args.target, options=opts)))
        p = result.prepared
        body_assets(p.source_body.character, p.source_body.mapping)  # the source body's grids, as in a job
        frames = result.after.num_frames
        out: dict[str, Any] = {"motion": args.motion.name, "target": p.target.character.name, "frames": frames}
        reports = {}
        for label, every in (("every frame (before issue 20)", True), ("default", False)):
            best = math.inf
            for _ in range(args.repeats):
                with timer() as took:
                    job = measure_job(
                        p.source_body.character, p.source_body.mapping, p.source_view, p.target.character,
                        p.target.mapping, p.before, result.after, source_contacts=p.contacts, constraints=p.constraints,
                        context=job_context(result), notes=list(result.warnings), threads=None, every_frame=every,
                    )  # fmt: skip
                best = min(best, took.wall_s)
            reports[label] = job.report.model_dump(mode="json")
            out[label] = {"ms_per_frame": round(1000 * best / frames, 2), "timings_s": job.report.timings_s}
            print(f"  {label:<32} {1000 * best / frames:8.2f} ms/frame  {job.report.timings_s}")
    a, b = ({k: v for k, v in r.items() if k not in ("timings_s", "context")} for r in reports.values())
    out["report_differences"] = _numbers_differ(a, b)
    out["machine"] = machine()
    print(f"  reports differ at {len(out['report_differences'])} places")
    write_json(args.output.with_name("metrics_job_benchmark.json"), out)


if __name__ == "__main__":
    main()
