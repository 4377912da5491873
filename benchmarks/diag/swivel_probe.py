"""How far an elbow swivel alone can take the frames deeper than 1 cm (issue 22, item 3): one clip x body through
the default chain without the swivel stage, then each arm turned about its shoulder-to-wrist line by the angle
of a grid that makes its judged depth (sampled, `contacts/arm_depth.py`) shallowest on each frame, raw and
smoothed in time, and the stage itself; the judge's figures after each (ACCEPTANCE.md, as `retarget eval`
measures them). The swivel keeps the hands, so end-effector error and contacts cannot change. Each ``--swivel
KEY=VALUE[,KEY=VALUE]`` adds a row of the stage with those numeric settings of ``SwivelParams`` changed (e.g.
``step_cost_m=0.02,smooth_seconds=0.0667``); the stage's rows print its report too.

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/diag/swivel_probe.py \\
        ../shared/data/motions/cmu/005_17.bvh ~/.cache/retarget/heldout/heldout_skinny-86cd9535396e.glb --frames 300
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

from retarget_core.contacts.hand_reach import reach_body
from retarget_core.metrics.acceptance import figures_from_measures, measure_acceptance
from retarget_core.motion import Motion
from retarget_core.pipeline import refine, refine_context
from retarget_core.refine import arm_swivel
from retarget_core.refine.arms import arms_of, swivel_arms
from retarget_core.refine.temporal import weighted_smooth

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, write_json  # noqa: E402

GRID_DEG = (0, -5, 5, -10, 10, -20, 20, -30, 30, -45, 45, -60, 60, -90, 90)  # smaller turns first: kept on ties
FIGURES = ("pen_percent", "frames_over_1cm_percent", "end_effector_error_cm", "jerk_ratio", "contact_preservation",
           "false_contacts")  # fmt: skip


def main() -> None:
    ap = case_parser(__doc__, frames=300)
    ap.add_argument("--swivel", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]")
    a = ap.parse_args()
    torch.set_num_threads(2)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    prep = case.prepared
    options = prep.inputs.options.model_copy(deep=True)
    options.stages.arm_swivel = False
    chain = refine(prep, options=options).after
    ctx, target = refine_context(prep), prep.target
    rows = []

    def report(label: str, motion: Motion) -> None:
        f = figures_from_measures(measure_acceptance(target.character, target.mapping, motion), case.source)
        row = {"variant": label, **{k: None if getattr(f, k) is None else round(float(getattr(f, k)), 4) for k in FIGURES}}
        rows.append(row)
        print(f"{label:>16}: " + "  ".join(f"{k} {row[k]}" for k in FIGURES), flush=True)

    print(f"{a.clip.stem} x {Path(a.body).stem}, {chain.num_frames} frames")
    report("copy", prep.before)
    report("chain", chain)
    arms = arms_of(target.mapping, target.character.skeleton.parents)
    rb = reach_body(target.character, target.mapping)
    frames = torch.arange(chain.num_frames)
    depth = torch.stack([arm_swivel.arm_depths(ctx, rb, swivel_arms(chain, arms, torch.full((len(frames), 2), math.radians(g),
                         dtype=torch.float64)), frames, [0, 1], 64) for g in GRID_DEG])  # fmt: skip
    best = torch.tensor(GRID_DEG, dtype=torch.float64)[depth.argmin(dim=0)]  # (F, 2) degrees
    turned = best[best != 0].abs()
    print(f"turned arm-frames {len(turned)} of {best.numel()}, of them 45 degrees or more: "
          f"{float((turned >= 45).double().mean()) * 100 if len(turned) else 0:.0f} %")
    report("best per frame", swivel_arms(chain, arms, torch.deg2rad(best)))
    weight = torch.where(best != 0, 1.0, 0.2).double()
    smooth = torch.stack([weighted_smooth(torch.deg2rad(best[:, s : s + 1]), weight[:, s], 0.1 * chain.fps)[:, 0]
                          for s in range(2)], dim=1)  # fmt: skip
    report("smoothed", swivel_arms(chain, arms, smooth))
    for label, params in [("stage", arm_swivel.SwivelParams()), *(_variant(v) for v in a.swivel)]:
        outcome = arm_swivel.run(ctx, chain, params)
        report(label, outcome.motion)
        print(f"{'':>16}  stage report: {outcome.report}", flush=True)
    if a.json:
        write_json(a.json, {"clip": a.clip.stem, "body": a.body, "frames": chain.num_frames, "rows": rows})


def _variant(text: str) -> tuple[str, arm_swivel.SwivelParams]:
    """A ``--swivel`` argument as its row label and the stage's settings."""
    changes = {k: float(v) for k, v in (kv.split("=", 1) for kv in text.split(","))}
    return f"stage {text}", arm_swivel.SwivelParams(**changes)  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
