"""Ablation of the collision stage's settings: each setting at its default against off (or neutral), on held-out
cases, measured by the judge (ACCEPTANCE.md, as `retarget eval` measures it) right after the collision stage of
the default chain (network and ESO before it; the foot lock after it is left out so the stage's own effect shows).

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/eval/collision_ablation.py [--frames 100] [--cases N]

Writes ablation.json and ablation.md in benchmarks/eval/results/collision_ablation/ (``--out-dir``): per variant
the mean judged figures over the cases and their change against the defaults, and the stage's CPU time. A setting earns its place when turning it off makes
a figure the product is judged on worse beyond the spread between cases.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from retarget_core.heldout import body_path, load_split
from retarget_core.metrics.acceptance import figures_from_measures, measure_acceptance
from retarget_core.pipeline import refine_context
from retarget_core.refine import collisions, load_stage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import clip_path, mean, parser, prepare_case, results_dir, timer, write_json  # noqa: E402

OUT = results_dir("eval") / "collision_ablation"
FIGURES = ("pen_percent", "frames_over_1cm_percent", "head_percent", "contact_preservation", "false_contacts",
           "end_effector_error_cm", "jerk_ratio", "foot_accuracy")  # fmt: skip
CASES = (("002_05", "heldout_heavy"), ("002_06", "heldout_tall"), ("002_08", "heldout_bulky"),
         ("005_12", "heldout_short"), ("005_18", "heldout_skinny"), ("005_17", "heldout_heavy"),
         ("005_02", "heldout_bulky"), ("001_01", "heldout_tall"), ("002_01", "heldout_short"),
         ("007_06", "heldout_skinny"))  # fmt: skip
"""Every held-out clip but one, each body twice."""

D = collisions.CollisionParams()
VARIANTS: dict[str, collisions.CollisionParams] = {
    "default": D,
    "repair_rounds=0": replace(D, repair_rounds=0),
    "finish_iterations=0": replace(D, finish_iterations=0),
    "use_mesh=False": replace(D, use_mesh=False),
    "judged_pairs_only=False": replace(D, judged_pairs_only=False),
    "judged_contacts=False": replace(D, judged_contacts=False),
    "w_ground=0": replace(D, w_ground=0.0),
    "w_pair=0": replace(D, w_pair=0.0),
    "contact_ee_weight=0.5": replace(D, contact_ee_weight=0.5),
    "planted_foot_ee_weight=0.5": replace(D, planted_foot_ee_weight=0.5),
    "ee_source_pull=0": replace(D, ee_source_pull={k: 0.0 for k in D.ee_source_pull}),
    "w_smooth=0": replace(D, w_smooth=0.0),
    "iterations=30": replace(D, iterations=30),  # fewer sentinel steps: what the stage's time buys
    "iterations=24": replace(D, iterations=24),
}
"""Each setting off, or at the neutral value (the other end effectors' weight, no pull)."""


def run_case(clip: str, body: str, frames: int, variants: dict[str, collisions.CollisionParams]) -> dict[str, Any]:
    """The judged figures after the collision stage with each variant on one case."""
    params = {p.name: p for p in load_split().bodies}
    case = prepare_case(clip_path(clip), str(body_path(params[body])), frames, "builtin:male_average")
    ctx = refine_context(case.prepared)
    target = case.prepared.target
    motion = case.prepared.before
    for name in ("recurrent", "eso"):
        motion = load_stage(name)(ctx, motion).motion
    out: dict[str, Any] = {}
    for label, p in variants.items():
        with timer() as took:
            result = collisions.resolve(ctx, motion, p).motion
        seconds = took.cpu_s
        f = figures_from_measures(measure_acceptance(target.character, target.mapping, result), case.source)
        out[label] = {"cpu_s": round(seconds, 2), **{k: _round(getattr(f, k)) for k in FIGURES}}
        print(f"{clip} x {body} {label}: " + " ".join(f"{k} {out[label][k]}" for k in FIGURES) + f" ({seconds:.1f} s)", flush=True)
    return out


def _round(v: float | None) -> float | None:
    return None if v is None else round(float(v), 4)


def summarise(rows: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per variant: the mean of each figure over the cases, its mean change against the default, and how many
    cases got worse / better by more than a tenth of the default's spread."""
    out: dict[str, dict[str, Any]] = {}
    for label in next(iter(rows.values())):
        fig: dict[str, Any] = {"cpu_s": mean([r[label]["cpu_s"] for r in rows.values()])}
        for k in FIGURES:
            vals = [(r[label][k], r["default"][k]) for r in rows.values() if r[label][k] is not None and r["default"][k] is not None]
            fig[k] = mean([v for v, _ in vals])
            fig[f"{k}_change"] = mean([v - d for v, d in vals])
        out[label] = fig
    return out


def write(rows: dict[str, dict[str, Any]], frames: int, seconds: float, out: Path) -> None:
    """``ablation.json`` (every case and the summary) and ``ablation.md`` (the summary's table) in ``out``."""
    summary = summarise(rows)
    write_json(out / "ablation.json", {"frames": frames, "seconds": round(seconds), "cases": rows,
                                       "summary": summary}, quiet=True)  # fmt: skip
    head = "| variant | cpu s | " + " | ".join(FIGURES) + " |"
    lines = [f"# Collision stage ablation ({len(rows)} held-out cases, {frames} frames, {seconds:.0f} s)", "",
             "Mean over the cases; in brackets the mean change against the defaults.", "", head,
             "|" + "---|" * (len(FIGURES) + 2)]  # fmt: skip
    for label, s in summary.items():
        cells = [f"{s[k]} ({s[k + '_change']:+.4f})" if s[k] is not None and s[k + "_change"] is not None else "-" for k in FIGURES]
        lines.append(f"| {label} | {s['cpu_s']} | " + " | ".join(cells) + " |")
    (out / "ablation.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--frames", type=int, default=100, help="first frames of each clip at 30 fps")
    ap.add_argument("--cases", type=int, default=len(CASES), help=f"the first N of the {len(CASES)} cases")
    ap.add_argument("-o", "--out-dir", type=Path, default=OUT, help="where ablation.json and ablation.md go")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
                    help="the variants to run (default: all; 'default' is always run)")
    a = ap.parse_args()
    variants = {k: v for k, v in VARIANTS.items() if k == "default" or k in a.variants}
    torch.set_num_threads(1)
    start = time.perf_counter()
    rows: dict[str, dict[str, Any]] = {}
    for clip, body in CASES[: a.cases]:
        rows[f"{clip} x {body}"] = run_case(clip, body, a.frames, variants)
        write(rows, a.frames, time.perf_counter() - start, a.out_dir)


if __name__ == "__main__":
    main()
