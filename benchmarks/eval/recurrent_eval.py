"""Copy vs network vs network + ESO on held-out clips x bodies (clips: retarget_core.model.data.HELD_OUT_CLIPS;
bodies: shared mh_* characters, which no training body is). Prints a table and writes
benchmarks/eval/results/recurrent_eval.json. Run under the heavy lock:

    flock /tmp/heavy.lock python benchmarks/eval/recurrent_eval.py [--frames 300] [--bodies mh_male_bulky ...]
        [--weights other.pt --out benchmarks/eval/results/recurrent_eval_other.json]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path

import torch

from retarget_core.cases import context_from_prepared, prepared_case
from retarget_core.measure import measure_job
from retarget_core.model import inference
from retarget_core.model.data import HELD_OUT_CLIPS
from retarget_core.refine import eso, recurrent

REPO = Path(__file__).resolve().parents[2]
FIGURES = (
    ("pen_%v", lambda s: s.penetrating_vertices_percent),
    ("pen_frames_%", lambda s: s.penetrating_frames_percent),
    ("pen_volume_cm3", lambda s: s.penetration_volume.value_at_180),
    ("contact_cm", lambda s: s.contact_distance_mean.value_at_180),
    ("contact_ok_%", lambda s: s.contact_satisfied_percent),
    ("foot_acc", lambda s: s.foot_contact_accuracy),
    ("skate_cm", lambda s: s.foot_skate.value_at_180),
    ("mpjpe_cm", lambda s: s.mpjpe.value_at_180),
    ("jerk", lambda s: s.jerk.value_at_180),
)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--clips", nargs="*", default=list(HELD_OUT_CLIPS))
    ap.add_argument("--bodies", nargs="*", default=["mh_male_bulky", "mh_female_average"])
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "eval" / "results" / "recurrent_eval.json")
    ap.add_argument("--weights", type=Path, default=None, help="weights to evaluate (default: the shipped ones)")
    args = ap.parse_args()
    if args.weights is not None:
        inference.WEIGHTS_PATH = args.weights
    torch.set_num_threads(1)
    rows = []
    for body in args.bodies:
        for clip in args.clips:
            prep = prepared_case(args.data / "motions" / "cmu" / f"{clip}.bvh", args.data / "characters" / f"{body}.glb", args.frames)
            ctx = context_from_prepared(prep)
            t = time.perf_counter()
            net = recurrent.run(ctx, ctx.before)
            net_ms = 1000 * (time.perf_counter() - t) / ctx.num_frames
            t = time.perf_counter()
            opt = eso.run(ctx, net.motion)
            eso_ms = 1000 * (time.perf_counter() - t) / ctx.num_frames
            row = {"clip": clip, "body": body, "frames": ctx.num_frames, "constraints": ctx.constraints.count,
                   "network_ms_per_frame": round(net_ms, 3), "eso_ms_per_frame": round(eso_ms, 3),
                   "network_report": net.report, "eso_report": {k: v for k, v in opt.report.items() if k != "constraint_moved_cm"},
                   "eso_constraint_moved_cm": opt.report.get("constraint_moved_cm", [])}  # fmt: skip
            for name, motion in (("network", net.motion), ("network+eso", opt.motion)):
                rep = measure_job(prep.source_body.character, prep.source_body.mapping, prep.source_view,
                                  prep.target.character, prep.target.mapping, ctx.before, motion,
                                  source_contacts=prep.contacts, constraints=prep.constraints, include_series=False).report  # fmt: skip
                assert rep.after is not None
                if "copy" not in row:
                    row["copy"] = {k: f(rep.before.summary) for k, f in FIGURES}
                row[name] = {k: f(rep.after.summary) for k, f in FIGURES}
            rows.append(row)
            print(json.dumps({k: row[k] for k in ("clip", "body", "frames", "constraints", "network_ms_per_frame", "eso_ms_per_frame")}), flush=True)
            for m in ("copy", "network", "network+eso"):
                print(f"  {m:12s} " + " ".join(f"{k}={v if v is None else round(v, 3)}" for k, v in row[m].items()), flush=True)
    means = {}
    for m in ("copy", "network", "network+eso"):
        means[m] = {k: _mean([r[m][k] for r in rows]) for k, _ in FIGURES}
    means["ms_per_frame"] = {"network": _mean([r["network_ms_per_frame"] for r in rows]), "eso": _mean([r["eso_ms_per_frame"] for r in rows])}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    weights = {"path": str(args.weights or inference.WEIGHTS_PATH.relative_to(REPO)), "config": asdict(inference.shipped_network().config)}
    args.out.write_text(json.dumps({"rows": rows, "means": means, "torch_threads": 1, "weights": weights}, indent=1))
    print(json.dumps(means, indent=1))


def _mean(xs: list[float | None]) -> float | None:
    v = [x for x in xs if x is not None]
    return round(sum(v) / len(v), 4) if v else None


if __name__ == "__main__":
    main()
