"""Copy vs network vs network + ESO on held-out clips x bodies (clips: retarget_core.model.data.HELD_OUT_CLIPS;
bodies: shared mh_* characters, which no training body is). Prints a table and writes
benchmarks/eval/results/recurrent_eval.json. Run under the heavy lock:

    flock /tmp/heavy.lock python benchmarks/eval/recurrent_eval.py [--frames 300] [--bodies mh_male_bulky ...]
        [--weights other.pt --out benchmarks/eval/results/recurrent_eval_other.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from retarget_core.cases import context_from_prepared, prepared_case
from retarget_core.measure import measure_job
from retarget_core.model import inference
from retarget_core.model.data import HELD_OUT_CLIPS
from retarget_core.refine import eso, recurrent

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    REPO,
    SHARED_DATA,
    add_output,
    machine,
    mean,
    parser,
    results_dir,
    timer,
    write_json,
)

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
METHODS = ("copy", "network", "network+eso")


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--data", type=Path, default=SHARED_DATA, help="the shared data set")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--clips", nargs="*", default=list(HELD_OUT_CLIPS))
    ap.add_argument("--bodies", nargs="*", default=["mh_male_bulky", "mh_female_average"])
    add_output(ap, results_dir("eval") / "recurrent_eval.json")
    ap.add_argument("--weights", type=Path, default=None, help="weights to evaluate (default: the shipped ones)")
    args = ap.parse_args()
    if args.weights is not None:
        inference.WEIGHTS_PATH = args.weights
    torch.set_num_threads(1)
    rows = [run_case(args, clip, body) for body in args.bodies for clip in args.clips]
    means: dict[str, Any] = {m: {k: mean([r[m][k] for r in rows]) for k, _ in FIGURES} for m in METHODS}
    means["ms_per_frame"] = {"network": mean([r["network_ms_per_frame"] for r in rows]),
                             "eso": mean([r["eso_ms_per_frame"] for r in rows])}  # fmt: skip
    weights = {"path": str(args.weights or inference.WEIGHTS_PATH.relative_to(REPO)),
               "config": asdict(inference.shipped_network().config)}  # fmt: skip
    print(json.dumps(means, indent=1))
    write_json(args.output, {"rows": rows, "means": means, "torch_threads": 1, "weights": weights, "machine": machine()})


def run_case(args: argparse.Namespace, clip: str, body: str) -> dict[str, Any]:
    """Copy, network and network + ESO on one clip x body: times, the stages' reports and the figures."""
    prep = prepared_case(args.data / "motions" / "cmu" / f"{clip}.bvh", args.data / "characters" / f"{body}.glb", args.frames)
    ctx = context_from_prepared(prep)
    with timer() as net_t:
        net = recurrent.run(ctx, ctx.before)
    with timer() as eso_t:
        opt = eso.run(ctx, net.motion)
    row: dict[str, Any] = {
        "clip": clip, "body": body, "frames": ctx.num_frames, "constraints": ctx.constraints.count,
        "network_ms_per_frame": net_t.ms_per_frame(ctx.num_frames), "eso_ms_per_frame": eso_t.ms_per_frame(ctx.num_frames),
        "network_report": net.report, "eso_report": {k: v for k, v in opt.report.items() if k != "constraint_moved_cm"},
        "eso_constraint_moved_cm": opt.report.get("constraint_moved_cm", []),
    }  # fmt: skip
    for name, motion in (("network", net.motion), ("network+eso", opt.motion)):
        rep = measure_job(prep.source_body.character, prep.source_body.mapping, prep.source_view,
                          prep.target.character, prep.target.mapping, ctx.before, motion,
                          source_contacts=prep.contacts, constraints=prep.constraints, include_series=False).report  # fmt: skip
        assert rep.after is not None
        row.setdefault("copy", {k: f(rep.before.summary) for k, f in FIGURES})
        row[name] = {k: f(rep.after.summary) for k, f in FIGURES}
    print(json.dumps({k: row[k] for k in ("clip", "body", "frames", "constraints", "network_ms_per_frame", "eso_ms_per_frame")}), flush=True)
    for m in METHODS:
        print(f"  {m:12s} " + " ".join(f"{k}={v if v is None else round(v, 3)}" for k, v in row[m].items()), flush=True)
    return row


if __name__ == "__main__":
    main()
