"""What each refinement stage does to the judge's figures: one clip x body through the default chain, the
acceptance figures (ACCEPTANCE.md, as `retarget eval` measures them), each end effector's error and the stage's
own report figures, printed after the copy and after every stage that ran, so a regression can be pinned on the
stage that made it.

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/diag/chain_diag.py \\
        ../shared/data/motions/cmu/002_06.bvh ~/.cache/retarget/heldout/heldout_tall-cc6a29d268ed.glb

The clip is sent as a GLB on the average body and resampled to 30 fps, as the held-out evaluation does (the
copy's and the last stage's rows are that evaluation's figures for the case); ``--frames`` (default 100) caps
its length. Optional ``--json`` writes the rows; ``--collisions KEY=VALUE`` (repeatable) runs the collision stage
with that numeric setting of ``CollisionParams`` changed (e.g. ``planted_foot_ee_weight=0.5``, or one entry of
a dict setting: ``end_effectors.LeftHand=2``); ``--hands KEY=VALUE`` the same for the hand contact stage's
``HandContactParams`` (e.g. ``passes=2``); ``--contacts`` also prints, per hand and part, the source contacts
kept and how far the lost ones are.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

from retarget_core.canonical import CANONICAL_JOINTS
from retarget_core.metrics.acceptance import END_EFFECTORS, ClipAcceptance, figures_from_measures, measure_acceptance
from retarget_core.metrics.acceptance_body import CONTACT_PARTS
from retarget_core.motion import Motion
from retarget_core.pipeline import refine_context
from retarget_core.refine import collisions, hand_contacts, refinement_stages

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, setting_overrides, write_json  # noqa: E402

FIGURES = ("pen_percent", "frames_over_1cm_percent", "contact_preservation", "false_contacts", "foot_accuracy",
           "end_effector_error_cm", "jerk_ratio", "ground_penetration_cm", "skate_cm", "head_percent")  # fmt: skip


def _rounded(value: float | None) -> float | None:
    """A figure to 4 decimals; None stays None (a clip without source contacts has no preservation)."""
    return None if value is None else round(float(value), 4)


def effector_errors(result: ClipAcceptance, source: ClipAcceptance) -> dict[str, float]:
    """Each end effector's share of the judge's end-effector error: its mean error (cm at 1.80 m) relative to
    the hips (the judge's figure is the mean of these over the effectors)."""
    f_n = min(result.num_frames, source.num_frames)
    hips = CANONICAL_JOINTS.index("Hips")
    out = {}
    for name in END_EFFECTORS:
        c = CANONICAL_JOINTS.index(name)
        rel_r = result.joints[:f_n, c] - result.joints[:f_n, hips]
        rel_s = source.joints[:f_n, c] - source.joints[:f_n, hips]
        err = np.linalg.norm(rel_r - rel_s, axis=-1)
        out[name] = round(100.0 * float(np.nanmean(err)), 2) if np.isfinite(err).any() else float("nan")
    return out


def contact_table(result: ClipAcceptance, source: ClipAcceptance) -> dict[str, str]:
    """Per (hand, contact part) with source contacts: ``kept/contacts`` and the result's median distance (cm at
    1.80 m) on the lost ones, the judge's contact preservation taken apart."""
    f_n = min(result.num_frames, source.num_frames)
    d_src, d_res = source.hand_distance[:f_n], result.hand_distance[:f_n]
    out = {}
    for h, hand in enumerate(("L", "R")):
        for c, part in enumerate(CONTACT_PARTS):
            touch = d_src[:, h, c] < 0.015
            if touch.any():
                lost = d_res[touch, h, c] >= 0.025
                med = f" lost@{100 * float(np.median(d_res[touch, h, c][lost])):.1f}" if lost.any() else ""
                out[f"{hand}:{part}"] = f"{int((~lost).sum())}/{int(touch.sum())}{med}"
    return out


def main() -> None:
    ap = case_parser(__doc__)
    ap.add_argument("--collisions", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--hands", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--contacts", action="store_true", help="also print each hand's kept source contacts per part")
    a = ap.parse_args()
    overrides = setting_overrides(collisions.CollisionParams(), a.collisions)
    collision_params = collisions.CollisionParams(**overrides)
    hand_overrides = setting_overrides(hand_contacts.HandContactParams(), a.hands)
    hand_params = hand_contacts.HandContactParams(**hand_overrides)
    torch.set_num_threads(1)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    prepared, source = case.prepared, case.source
    ctx = refine_context(prepared)
    target = prepared.target
    rows: list[dict[str, object]] = []

    def report(stage: str, motion: Motion, seconds: float) -> None:
        measured = measure_acceptance(target.character, target.mapping, motion)
        f = figures_from_measures(measured, source)
        row: dict[str, object] = {"stage": stage, "seconds": round(seconds, 2),
                                  **{k: _rounded(getattr(f, k)) for k in FIGURES},
                                  "end_effector_cm": effector_errors(measured, source)}  # fmt: skip
        rows.append(row)
        print(f"{stage:>12}: " + "  ".join(f"{k} {row[k]}" for k in FIGURES) + f"  ({seconds:.1f} s)", flush=True)
        print(f"{'':>12}  end effectors (cm): {row['end_effector_cm']}", flush=True)
        if a.contacts:
            print(f"{'':>12}  contacts kept: {contact_table(measured, source)}", flush=True)

    print(f"{a.clip.stem} x {Path(a.body).stem}, {prepared.before.num_frames} frames")
    report("copy", prepared.before, 0.0)
    motion = prepared.before
    for info, stage in refinement_stages():
        if stage is None or not prepared.inputs.options.stages.enabled(info.name):
            continue
        t = time.perf_counter()
        run = {
            "collisions": lambda c, m: collisions.resolve(c, m, collision_params),
            "hand_contacts": lambda c, m: hand_contacts.run(c, m, hand_params),
        }.get(info.name, stage)
        outcome = run(ctx, motion)
        motion = outcome.motion
        report(info.name, motion, time.perf_counter() - t)
        scalars = {k: v for k, v in outcome.report.items() if isinstance(v, (int, float)) and k != "seconds"}
        print(f"{'':>12}  stage report: {scalars}", flush=True)
    if a.json:
        write_json(a.json, {"clip": a.clip.stem, "body": a.body, "collisions": overrides, "hands": hand_overrides,
                            "rows": rows})  # fmt: skip


if __name__ == "__main__":
    main()
