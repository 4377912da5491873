"""Time every stage of contact detection, correspondence, SDF precomputation, metrics and energies.

Defaults: a 300-frame piece (at 30 fps) of CMU 02_08 (swordplay, two-hand grips) on the bulky shared body
(13,380 vertices), the source on the built-in body sized to the clip. Prints a table and writes JSON.

    python benchmarks/metrics_benchmark.py [--motion CLIP] [--target BODY] [--frames 300] [-o out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]
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
    ap.add_argument("-o", "--output", type=Path, default=REPO / "benchmarks" / "results" / "metrics_benchmark.json")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

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


if __name__ == "__main__":
    main()
