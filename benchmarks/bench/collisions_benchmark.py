"""Collision stage benchmark: ms per frame of the stage (wall and process CPU time: the CPU figure is the one to read on a shared machine) on 300-frame clips (30 fps) x heavy bodies, and its effect
measured by :mod:`retarget_core.metrics` (penetrating vertices %, frames whose deepest vertex is > 1 cm, contact
distance, jerk), before (plain rotation copy) and after. One torch thread. Writes
benchmarks/bench/results/collisions_benchmark.json.

    flock /tmp/heavy.lock env PYTHONPATH=$PWD .venv/bin/python benchmarks/bench/collisions_benchmark.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import torch

from retarget_core.body_parts import CLUSTERS
from retarget_core.cases import context_from_files
from retarget_core.context import RefineContext
from retarget_core.energy.sdf import PairSamples, sample_pairs, segment_matrices, vertex_depths
from retarget_core.metrics.compute import ClipMeasures, compute_metrics
from retarget_core.motion import Motion
from retarget_core.refine.collisions import resolve

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    add_output,
    character_path,
    clip_path,
    jerk,
    machine,
    parser,
    results_dir,
    timer,
    write_json,
)

DEFAULT_CLIPS = ("002_05", "002_08", "001_01", "005_12", "006_12")
DEFAULT_BODIES = ("mh_male_bulky", "mh_male_muscular", "mh_female_average")


# ACCEPTANCE.md's pairs: an arm vertex against torso, head, the other arm and both legs; a leg vertex against the
# other leg and both arms (torso-in-arm and head-in-torso are not in its pen %v).
JUDGE_PAIRS: dict[str, tuple[str, ...]] = {
    "left_arm": ("torso", "head", "right_arm", "left_leg", "right_leg"),
    "right_arm": ("torso", "head", "left_arm", "left_leg", "right_leg"),
    "left_leg": ("right_leg", "left_arm", "right_arm"),
    "right_leg": ("left_leg", "left_arm", "right_arm"),
}


def judge_like_penetration(ctx: RefineContext, m: Motion) -> dict[str, float]:
    """Pen %v and frames > 1 cm on the acceptance's pairs only (our SDF depths, geodesic weights: a proxy)."""
    parts = ctx.parts
    cl = torch.tensor(parts.cluster)
    tested = torch.zeros(len(CLUSTERS), len(CLUSTERS), dtype=torch.bool)
    for tester, others in JUDGE_PAIRS.items():
        for other in others:
            tested[CLUSTERS.index(tester), CLUSTERS.index(other)] = True
    s = ctx.sdf.scale_to_180
    f_n = m.num_frames
    pen, deep = torch.zeros(f_n), torch.zeros(f_n, dtype=torch.bool)
    with torch.no_grad():
        grot, gpos = m.global_transforms()
        for a in range(0, f_n, 64):
            e = min(f_n, a + 64)
            verts = ctx.target.pose_vertices(grot[a:e], gpos[a:e])
            sp = sample_pairs(ctx.sdf, verts, segment_matrices(ctx.target, parts, grot[a:e], gpos[a:e]))
            keep = tested[cl[parts.vertex_part[sp.vertex]], cl[sp.part]]
            sp = PairSamples(sp.frame[keep], sp.vertex[keep], sp.part[keep], sp.distance[keep])
            d = vertex_depths(ctx.sdf, sp, e - a) * s
            pen[a:e] = (d > 0.003).float().mean(-1) * 100.0
            deep[a:e] = d.amax(-1) > 0.01
    return {"judge_pairs_pen_percent": round(float(pen.mean()), 4),
            "judge_pairs_frames_deeper_than_1cm_percent": round(float(deep.float().mean() * 100.0), 2)}  # fmt: skip


def _figures(ctx: RefineContext, m: Motion, original: ClipMeasures | None) -> tuple[dict[str, Any], ClipMeasures]:
    metrics, measures = compute_metrics(ctx.target, ctx.target_mapping, ctx.sdf, m, contacts=ctx.constraints,
                                        original=original, source_feet=ctx.feet)  # fmt: skip
    s = metrics.summary
    deep = measures.vertex_depth.amax(-1) * measures.scale_to_180 > 0.01
    return {
        "penetrating_vertices_percent": s.penetrating_vertices_percent,
        "frames_deeper_than_1cm_percent": round(float(deep.float().mean() * 100.0), 2),
        "max_depth_cm_at_180": s.penetration_max_depth.value_at_180,
        "contact_distance_mean_cm_at_180": s.contact_distance_mean.value_at_180,
        "contact_satisfied_percent": s.contact_satisfied_percent,
        "m_c": s.m_c.value_at_180,
        "mpjpe_cm_at_180": s.mpjpe.value_at_180,
        "jerk_at_180": jerk(m, ctx.target.height),
        **judge_like_penetration(ctx, m),
    }, measures


def bench_one(clip: str, body: str, frames: int, fps: float) -> dict[str, Any]:
    ctx = context_from_files(clip_path(clip), character_path(body), 0, frames, fps)
    with timer() as took:
        out = resolve(ctx, ctx.before)
    seconds, cpu_seconds = took.wall_s, took.cpu_s
    before, measures = _figures(ctx, ctx.before, None)
    after, _ = _figures(ctx, out.motion, measures)
    src_jerk = jerk(ctx.source_view, ctx.source_body.height)
    row = {
        "clip": clip, "body": body, "frames": ctx.num_frames, "contact_constraints": ctx.constraints.count,
        "stage_seconds": round(seconds, 3), "ms_per_frame": round(1000.0 * seconds / ctx.num_frames, 2),
        "stage_cpu_seconds": round(cpu_seconds, 3), "cpu_ms_per_frame": round(1000.0 * cpu_seconds / ctx.num_frames, 2),
        "contacts_kept_hand_to_part": out.report.get("contacts", {}).get("kept_after"),
        "before": before, "after": after,
        "pen_ratio": _ratio(after["penetrating_vertices_percent"], before["penetrating_vertices_percent"]),
        "deep_frames_ratio": _ratio(after["frames_deeper_than_1cm_percent"], before["frames_deeper_than_1cm_percent"]),
        "judge_pairs_pen_ratio": _ratio(after["judge_pairs_pen_percent"], before["judge_pairs_pen_percent"]),
        "judge_pairs_deep_frames_ratio": _ratio(after["judge_pairs_frames_deeper_than_1cm_percent"],
                                                before["judge_pairs_frames_deeper_than_1cm_percent"]),
        "jerk_ratio_vs_before": _ratio(after["jerk_at_180"], before["jerk_at_180"]),
        "jerk_ratio_vs_source": _ratio(after["jerk_at_180"], src_jerk),
        "stage_report": out.report,
    }  # fmt: skip
    return row


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or b == 0:
        return None
    return round(a / b, 4)


def _write(rows: list[dict[str, Any]], out: Path) -> dict[str, Any]:
    """Write the rows so far and their summary to ``out`` (after every row: a long run leaves its results)."""
    summary = {
        "rows": len(rows),
        "ms_per_frame_mean": round(sum(r["ms_per_frame"] for r in rows) / len(rows), 2),
        "cpu_ms_per_frame_mean": round(sum(r["cpu_ms_per_frame"] for r in rows) / len(rows), 2),
        "pen_ratio_max": max((r["pen_ratio"] for r in rows if r["pen_ratio"] is not None), default=None),
        "deep_frames_ratio_max": max((r["deep_frames_ratio"] for r in rows if r["deep_frames_ratio"] is not None), default=None),
        "judge_pairs_pen_ratio_max": max((r["judge_pairs_pen_ratio"] for r in rows if r["judge_pairs_pen_ratio"] is not None), default=None),
        "judge_pairs_deep_frames_ratio_max": max((r["judge_pairs_deep_frames_ratio"] for r in rows
                                                  if r["judge_pairs_deep_frames_ratio"] is not None), default=None),
        "jerk_ratio_vs_before_max": max((r["jerk_ratio_vs_before"] for r in rows if r["jerk_ratio_vs_before"] is not None), default=None),
        "torch_threads": torch.get_num_threads(),
    }  # fmt: skip
    write_json(out, {"summary": summary, "machine": machine(), "results": rows}, quiet=True)
    return summary


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--clips", nargs="*", default=list(DEFAULT_CLIPS))
    ap.add_argument("--bodies", nargs="*", default=list(DEFAULT_BODIES))
    ap.add_argument("--pairs", nargs="*", default=None, help="clip:body pairs, run in this order (instead of clips x bodies)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--fps", type=float, default=30.0)
    add_output(ap, results_dir("bench") / "collisions_benchmark.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    pairs = [tuple(p.split(":")) for p in args.pairs] if args.pairs else [(c, b) for b in args.bodies for c in args.clips]
    for clip, body in pairs:
        row = bench_one(clip, body, args.frames, args.fps)
        rows.append(row)
        b, a = row["before"], row["after"]
        print(f"{clip} {body}: {row['ms_per_frame']:.1f} ms/frame wall, {row['cpu_ms_per_frame']:.1f} CPU | pen %v {b['penetrating_vertices_percent']:.3f} -> "
              f"{a['penetrating_vertices_percent']:.3f} | >1cm {b['frames_deeper_than_1cm_percent']:.1f}% -> "
              f"{a['frames_deeper_than_1cm_percent']:.1f}% | judge pairs %v {b['judge_pairs_pen_percent']:.3f} -> "
              f"{a['judge_pairs_pen_percent']:.3f}, >1cm {b['judge_pairs_frames_deeper_than_1cm_percent']:.1f}% -> "
              f"{a['judge_pairs_frames_deeper_than_1cm_percent']:.1f}% | contact cm {b['contact_distance_mean_cm_at_180']} -> "
              f"{a['contact_distance_mean_cm_at_180']} (hand-part kept {row['contacts_kept_hand_to_part']}) | jerk x{row['jerk_ratio_vs_before']} (vs source "
              f"x{row['jerk_ratio_vs_source']})", flush=True)  # fmt: skip
        _write(rows, args.output)
    print(json.dumps(_write(rows, args.output)))


if __name__ == "__main__":
    main()
