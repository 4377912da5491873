"""What the hand contact stage wants and what its smoothing gives, frame by frame: one clip x body through the
default chain up to the stage, then one pass of its moves for one hand, printed on every frame where that hand is
deeper than ``--deeper`` cm (at 1.80 m) in a part: the depth, the way out of its deepest sampled vertex, the
wanted wrist move, the smoothed move and the depth after that one pass (all cm at 1.80 m). Shows where the
smoothing in time averages a short press away (docs/contacts.md, "Why 0.05 s and three passes").

    PYTHONPATH=. flock /tmp/heavy.lock .venv/bin/python benchmarks/diag/hand_moves.py \\
        ../shared/data/motions/cmu/002_01.bvh ~/.cache/retarget/heldout/heldout_tall-*.glb --frames 300 --hand left

``--hands KEY=VALUE`` (repeatable) changes a numeric setting of ``HandContactParams`` (e.g. ``smooth_seconds=0.1``).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch

from retarget_core.contacts.hand_depth import hand_tests
from retarget_core.contacts.hand_reach import reach_body
from retarget_core.motion import Motion
from retarget_core.pipeline import refine, refine_context
from retarget_core.refine import hand_contacts as hc
from retarget_core.refine.arms import arms_of
from retarget_core.stages import REFINEMENT_STAGE_NAMES

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import HeldoutCase, case_parser, prepare_case, setting_overrides, write_json  # noqa: E402


def chain_before_hands(case: HeldoutCase) -> tuple[Any, Motion]:
    """The refine context and the default chain's motion up to (not with) the hand contact stage."""
    prepared = case.prepared
    options = prepared.inputs.options.model_copy(deep=True)
    for name in REFINEMENT_STAGE_NAMES[REFINEMENT_STAGE_NAMES.index("hand_contacts") :]:
        setattr(options.stages, name, False)
    return refine_context(prepared), refine(prepared, options=options).after


def one_pass(ctx: Any, motion: Motion, side: int, deeper_cm: float, p: hc.HandContactParams) -> list[dict[str, Any]]:
    """Per frame where hand ``side`` is deeper than ``deeper_cm`` in a part: depth, way out, wanted and smoothed
    moves and the depth after one pass of the stage's moves (cm at 1.80 m)."""
    arms = arms_of(ctx.target_mapping, ctx.target.skeleton.parents)
    rb = reach_body(ctx.target, ctx.target_mapping)
    src, every = hc.source_groups(ctx), torch.arange(motion.num_frames)
    state, inside = hc.measure_both(ctx, rb, motion, src, p, every)
    want, step = hc.pass_moves(src, state, inside, motion, arms, rb.scale, p, hc.group_bones(ctx))
    _, after = hc.measure_both(ctx, rb, hc.apply_moves(motion, arms, step, p.max_reach), src, p, every)
    cm = 100.0 / rb.scale
    rows = []
    for f in range(motion.num_frames):
        g = int(inside.depth[f, side].argmax())
        depth = float(inside.depth[f, side, g]) * cm
        if depth <= deeper_cm:
            continue
        way = (inside.surface_point[f, side, g] - inside.hand_point[f, side, g]) * cm
        rows.append({"frame": f, "part": hand_tests(side)[g], "depth": round(depth, 2),
                     "way_out": [round(float(x), 2) for x in way], "wanted": [round(float(x), 2) for x in want[f, side] * cm],
                     "smoothed": [round(float(x), 2) for x in step[f, side] * cm],
                     "depth_after": round(float(after.depth[f, side, g]) * cm, 2)})  # fmt: skip
    return rows


def main() -> None:
    ap = case_parser(__doc__, frames=300)
    ap.add_argument("--hand", choices=("left", "right"), default="left")
    ap.add_argument("--deeper", type=float, default=0.5, help="cm at 1.80 m")
    ap.add_argument("--hands", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args()
    torch.set_num_threads(1)
    p = hc.HandContactParams(**setting_overrides(hc.HandContactParams(), a.hands))
    ctx, motion = chain_before_hands(prepare_case(a.clip, a.body, a.frames, a.source_body))
    rows = one_pass(ctx, motion, 0 if a.hand == "left" else 1, a.deeper, p)
    for r in rows:
        print(f"{r['frame']:4d} {r['part']:>9} depth {r['depth']:5.2f}  way out {r['way_out']}  wanted {r['wanted']}  "
              f"smoothed {r['smoothed']}  after one pass {r['depth_after']:5.2f}")  # fmt: skip
    if a.json:
        write_json(a.json, {"clip": a.clip.stem, "body": Path(a.body).stem, "hand": a.hand, "settings": vars(p),
                            "rows": rows})  # fmt: skip


if __name__ == "__main__":
    main()
