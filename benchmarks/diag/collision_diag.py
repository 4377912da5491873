"""Why frames stay deeper than 1 cm after the collision stage: for one clip x body, every frame the judge
counts (deepest counted limb vertex > 1 cm, at 1.80 m) before and after the stage alone, with the part pair
(the vertex's part, the part it is inside), the depth the judge sees, the depth the stage's own SDF check sees
for that vertex (weighted, beyond rest), whether the stage optimised the frame and the never-worse fallback
weight it kept there. The clip is resampled to 30 fps as `retarget eval` does, so the frames are the
evaluation's.

    PYTHONPATH=. RETARGET_CACHE_DIR=/tmp/rcache-coll flock /tmp/heavy.lock python benchmarks/diag/collision_diag.py \
        /work/shared/data/motions/cmu/005_02.bvh /root/.cache/retarget/heldout/heldout_skinny-86cd9535396e.glb
"""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import numpy as np
import torch

from retarget_core.geometry.judged_pairs import judged_allowed
from retarget_core.metrics.acceptance import _frame, _plan, figures_from_measures, measure_acceptance
from retarget_core.metrics.acceptance_body import PARTS, acceptance_body
from retarget_core.pipeline import refine_context
from retarget_core.refine import collisions
from retarget_core.refine.collision_check import check_frames, contact_instances
from retarget_core.resample import resample

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import JUDGE_FPS, case_parser, prepare_case, write_json  # noqa: E402


def part_pairs(character, mapping, posed: np.ndarray) -> list[tuple[str, str, float, int]]:
    """``(vertex part, inside part, depth m, vertex)`` of the deepest counted vertex per penetrated part."""
    body = acceptance_body(character, mapping)
    plan = _plan(body)
    out = []
    for t in PARTS:
        p2 = copy.copy(plan)
        p2.tester_cluster = {k: (v if k == t else np.zeros_like(v)) for k, v in plan.tester_cluster.items()}
        p2.tester_vertex = {k: (v if k == t else np.zeros_like(v)) for k, v in plan.tester_vertex.items()}
        p2.hand_cluster = {k: {} for k in plan.hand_cluster}
        depth, _ = _frame(body, p2, posed, 0.0)
        depth[body.part_of_vertex == PARTS.index("head")] = 0.0
        if depth.max() > 0:
            v = int(depth.argmax())
            out.append((PARTS[body.part_of_vertex[v]], t, float(depth[v]), v))
    return sorted(out, key=lambda x: -x[2])


def main() -> None:
    a = case_parser(None, frames=150).parse_args()
    torch.set_num_threads(1)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body, method="copy")
    prepared, src = case.prepared, case.source
    ctx = refine_context(prepared)
    tgt = prepared.target
    ch, sdf = tgt.character, ctx.sdf
    scale = sdf.scale_to_180
    outcome = collisions.resolve(ctx, prepared.before, collisions.CollisionParams(trace=True))
    rep = outcome.report
    trace = rep.pop("trace")
    m_before = measure_acceptance(ch, tgt.mapping, prepared.before)
    m_after = measure_acceptance(ch, tgt.mapping, outcome.motion)
    fb, fa = figures_from_measures(m_before, src), figures_from_measures(m_after, src)
    contacts = contact_instances(sdf, ctx.constraints)
    f_n = prepared.before.num_frames
    chk = check_frames(ch, sdf, outcome.motion.rotations.float(), outcome.motion.translations.float(), torch.arange(f_n),
                       contacts, 0.003 / scale, allowed=judged_allowed(sdf))  # fmt: skip
    print(f"{Path(a.clip).stem} x {ch.name}: pen %v {fb.pen_percent:.3f} -> {fa.pen_percent:.3f}, frames>1cm "
          f"{fb.frames_over_1cm_percent:.1f} -> {fa.frames_over_1cm_percent:.1f}, contact pres. {fb.contact_preservation} -> "
          f"{fa.contact_preservation}, EE {fb.end_effector_error_cm:.2f} -> {fa.end_effector_error_cm:.2f}, "
          f"jerk {fa.jerk_ratio}")  # fmt: skip
    print("stage:", json.dumps({k: v for k, v in rep.items() if k not in ("energy_terms",)}))
    active = set(trace["active"])
    weight = trace["weight"]
    judged = resample(outcome.motion, JUDGE_FPS) if abs(outcome.motion.fps - JUDGE_FPS) > 1e-6 else outcome.motion
    grot, gpos = judged.global_transforms()
    ratio = outcome.motion.fps / JUDGE_FPS  # stage frame of judge frame f: round(f * ratio)
    rows = []
    deep_after = np.nonzero(m_after.pen_max > 0.01)[0]
    for f in deep_after:
        posed = ch.pose_vertices(grot[f : f + 1], gpos[f : f + 1])[0].double().numpy()
        pairs = part_pairs(ch, tgt.mapping, posed)
        v = pairs[0][3] if pairs else -1
        fs = min(round(f * ratio), f_n - 1)
        stage_depth = float(chk.depth.value_at(torch.tensor([fs]), torch.tensor([v]))[0]) * scale if v >= 0 else 0.0
        rows.append({
            "frame": int(f), "before_cm": round(float(m_before.pen_max[f]) * 100, 2),
            "after_cm": round(float(m_after.pen_max[f]) * 100, 2),
            "pairs": [(p, q, round(d * scale * 100, 2)) for p, q, d, _ in pairs[:3]],
            "vertex": v, "stage_depth_cm": round(stage_depth * 100, 2),
            "geo_w": round(float(sdf.geodesic_weight[v].min()), 2) if v >= 0 else None,
            "optimised": fs in active, "weight": round(weight[fs], 2),
        })  # fmt: skip
    print(f"{len(deep_after)} frames > 1 cm after ({int((m_before.pen_max > 0.01).sum())} before); worse frames: "
          f"{int(((m_after.pen_max > 0.01) & (m_before.pen_max <= 0.01)).sum())}")  # fmt: skip
    for r in rows:
        print(r)
    # Contact losses (the judge's source contacts lost after, kept before).
    sd, bd, ad = src.hand_distance, m_before.hand_distance, m_after.hand_distance
    n = min(len(sd), len(ad))
    lost = (sd[:n] < 0.015) & (ad[:n] >= 0.025)
    lost_b = (sd[:n] < 0.015) & (bd[:n] >= 0.025)
    print(f"source contacts {int((sd[:n] < 0.015).sum())}, lost before {int(lost_b.sum())}, lost after {int(lost.sum())}")
    for f, h, c in zip(*np.nonzero(lost & ~lost_b), strict=True):
        print(f"  lost f{f} hand {h} part {c}: src {sd[f, h, c] * 100:.1f} before {bd[f, h, c] * 100:.1f} after "
              f"{ad[f, h, c] * 100:.1f} cm, optimised {round(f * ratio) in active}, weight {weight[min(round(f * ratio), f_n - 1)]:.2f}")  # fmt: skip
    # Which part pairs make the judged frames > 1 cm, before and after (counts of frames by deepest pair).
    from collections import Counter

    jb = resample(prepared.before, JUDGE_FPS) if abs(prepared.before.fps - JUDGE_FPS) > 1e-6 else prepared.before
    for label, mot, meas in (("before", jb, m_before), ("after", judged, m_after)):
        gr, gp = mot.global_transforms()
        cnt: Counter = Counter()
        for f in np.nonzero(meas.pen_max > 0.01)[0]:
            posed = ch.pose_vertices(gr[f : f + 1], gp[f : f + 1])[0].double().numpy()
            pairs = part_pairs(ch, tgt.mapping, posed)
            if pairs:
                cnt[f"{pairs[0][0]}>{pairs[0][1]}"] += 1
        print(f"deepest pairs of frames > 1 cm {label}: {dict(cnt)}")
    if a.json:
        write_json(a.json, {"rows": rows, "report": rep})


if __name__ == "__main__":
    main()
