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
import json
import math
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("RETARGET_SHARED_DATA", REPO.parent / "shared" / "data"))


CPU: dict[str, float] = {}


def timed(results: dict[str, float], name: str, fn: Callable[[], Any]) -> Any:
    """Run ``fn``, record its wall-clock seconds in ``results`` and its process CPU seconds in ``CPU``."""
    start, cpu = time.perf_counter(), time.process_time()
    out = fn()
    results[name] = round(time.perf_counter() - start, 3)
    CPU[name] = round(time.process_time() - cpu, 3)
    print(f"  {name:<40} {results[name]:8.3f} s wall {CPU[name]:8.3f} s cpu", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motion", type=Path, default=DATA / "motions" / "cmu" / "002_08.bvh")
    ap.add_argument("--target", default=str(DATA / "characters" / "mh_male_bulky.glb"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's own choice)")
    ap.add_argument("-o", "--output", type=Path, default=REPO / "benchmarks" / "bench" / "results" / "metrics_benchmark.json")
    ap.add_argument("--job", action="store_true", help="time the job's metrics stage, default vs every frame")
    ap.add_argument("--repeats", type=int, default=2, help="--job: timed runs of each path (the best is kept)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.job:
        job_metrics(args)
        return

    from retarget_core.body_parts import body_parts
    from retarget_core.contacts.correspondence import build_correspondence, transfer_contacts
    from retarget_core.contacts.foot_contact import detect_foot_contacts
    from retarget_core.contacts.self_contact import detect_self_contacts
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.energy.sdf import build_part_sdf, sample_pairs, segment_matrices, vertex_depths
    from retarget_core.energy.terms import interpenetration_energy, vertex_contact_energy
    from retarget_core.loading import load_character, load_motion
    from retarget_core.measure import SourceContactResult, source_contacts_model
    from retarget_core.metrics.compute import measure_clip, summarize
    from retarget_core.metrics.report import build_metrics_report, write_metrics_json
    from retarget_core.resample import resample
    from retarget_core.source_body import source_body_for

    t: dict[str, float] = {}
    print(f"benchmark: {args.motion.name} on {Path(args.target).name}, {args.frames} frames at {args.fps} fps")
    src = timed(t, "read motion", lambda: load_motion(args.motion))
    src.motion = resample(src.motion, args.fps).slice(0, args.frames)
    tgt = timed(t, "read target", lambda: load_character(args.target))
    body, body_map = timed(t, "source body (built-in, sized)", lambda: source_body_for(src.motion.skeleton, src.mapping))
    view = timed(t, "copy onto source body", lambda: copy_retarget(src.motion, src.mapping, body.skeleton, body_map))
    before = timed(t, "copy onto target", lambda: copy_retarget(src.motion, src.mapping, tgt.character.skeleton, tgt.mapping))
    frames = view.num_frames
    grot, gpos = view.global_transforms()
    with torch.no_grad():
        posed = timed(t, "skin source body (LBS)", lambda: body.pose_vertices(grot, gpos))
    parts = body_parts(body, body_map)
    sc = timed(t, "hand self-contacts (source)", lambda: detect_self_contacts(parts, posed, body.height, view.fps))
    _, rest = body.skeleton.rest_global()
    feet = timed(t, "foot contacts (source)", lambda: detect_foot_contacts(gpos, rest, body_map, body.height, view.fps))
    corr = timed(t, "correspondence features + KD-tree", lambda: build_correspondence(body, body_map, tgt.character, tgt.mapping))
    cons = timed(t, "transfer contacts", lambda: transfer_contacts(sc, corr))
    tparts = body_parts(tgt.character, tgt.mapping)
    sdf = timed(t, "part SDF grids (target, once per body)", lambda: build_part_sdf(tgt.character, tparts))
    measures = timed(t, "measure before (pose + SDF queries)", lambda: measure_clip(tgt.character, tgt.mapping, sdf, before, cons))
    metrics = timed(t, "summarise metrics", lambda: summarize(measures, source_feet=feet))
    found = SourceContactResult(sc, feet, body.name)
    report = build_metrics_report(
        before.name, tgt.character.name, tgt.character.height, metrics, source_contacts=source_contacts_model(found, cons),
        timings_s={k: v for k, v in t.items() if k in ("hand self-contacts (source)", "measure before (pose + SDF queries)")},
    )
    timed(t, "write metrics JSON", lambda: write_metrics_json(report, args.output.with_name("metrics_benchmark_report.json")))

    # Energies: E_int and E_j2j on every frame, forward and backward through skinning.
    tr, tp = before.global_transforms()
    tp = tp.clone().requires_grad_(True)

    def energies() -> float:
        verts = tgt.character.pose_vertices(tr, tp)
        mats = segment_matrices(tgt.character, tparts, tr, tp)
        e = interpenetration_energy(sdf, verts, mats) + vertex_contact_energy(verts, cons, tgt.character.height)
        e.sum().backward()
        return float(e.detach().sum())

    timed(t, "E_int + E_j2j forward+backward", energies)
    with torch.no_grad():
        v1 = tgt.character.pose_vertices(tr[:1], tp[:1].detach())
        m1 = segment_matrices(tgt.character, tparts, tr[:1], tp[:1].detach())
        timed(t, "penetration query, one frame", lambda: vertex_depths(sdf, sample_pairs(sdf, v1, m1), 1))

    summary = metrics.summary
    out = {
        "motion": args.motion.name,
        "target": tgt.character.name,
        "frames": frames,
        "fps": view.fps,
        "target_vertices": tgt.character.num_vertices,
        "target_triangles": int(tgt.character.faces.shape[0]),
        "source_contacts": sc.count,
        "constraints": cons.count,
        "seconds": t,
        "cpu_seconds": CPU,
        "per_job_seconds_excluding_reads_and_sdf": round(
            sum(v for k, v in t.items() if not k.startswith(("read", "part SDF", "E_int", "penetration query"))), 3
        ),
        "penetration_volume_cm3_at_180": summary.penetration_volume.value_at_180,
        "machine": {
            "cpu_count": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "platform": platform.platform(),
        },
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(out, indent=1))
    print(f"per job (contacts, correspondence, metrics; no file reads, SDF cached): {out['per_job_seconds_excluding_reads_and_sdf']} s")
    print(f"wrote {args.output}")


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
    from retarget_core.loading import load_motion
    from retarget_core.measure import measure_job, torch_threads
    from retarget_core.metrics_summary import job_context
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import PIPELINE_THREADS, prepare, refine

    src_fps = load_motion(args.motion).motion.fps
    opts = RetargetOptions(fps=args.fps, frame_end=max(2, int(round((args.frames - 1) * src_fps / args.fps)) + 1))
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
                start = time.perf_counter()
                job = measure_job(
                    p.source_body.character, p.source_body.mapping, p.source_view, p.target.character,
                    p.target.mapping, p.before, result.after, source_contacts=p.contacts, constraints=p.constraints,
                    context=job_context(result), notes=list(result.warnings), threads=None, every_frame=every,
                )  # fmt: skip
                best = min(best, time.perf_counter() - start)
            reports[label] = job.report.model_dump(mode="json")
            out[label] = {"ms_per_frame": round(1000 * best / frames, 2), "timings_s": job.report.timings_s}
            print(f"  {label:<32} {1000 * best / frames:8.2f} ms/frame  {job.report.timings_s}")
    a, b = ({k: v for k, v in r.items() if k not in ("timings_s", "context")} for r in reports.values())
    out["report_differences"] = _numbers_differ(a, b)
    out["machine"] = {"cpu_count": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2),
                      "platform": platform.platform()}  # fmt: skip
    print(f"  reports differ at {len(out['report_differences'])} places")
    path = args.output.with_name("metrics_job_benchmark.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
