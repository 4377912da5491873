"""Where one step of the collision solver goes: the energy's forward, forward and backward, and its pieces (forward
kinematics, posing the rows, the penetration and contact lookups), timed on the sentinel pass's first term set of
a job's clip (the bulky sample and 300 frames of CMU 02_08 by default; the copy as the stage's input), then the
whole stage (``resolve``) once warm, with its phases' CPU seconds.

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/diag/collision_step_profile.py [--motion CLIP] [--frames 300]
        [--target BODY] [-o out.json]
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from retarget_core.geometry.point_poser import pose_rows
from retarget_core.jobs import JobInputs
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import prepare, refine_context
from retarget_core.refine import collision_solver as solver
from retarget_core.refine import collisions
from retarget_core.refine.collision_terms import build_terms, read_rows

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    BULKY_SAMPLE,
    add_clip_options,
    add_output,
    machine,
    parser,
    results_dir,
    source_frames,
    write_json,
)


def ms(fn: Callable[[], Any], runs: int = 10) -> float:
    """Mean milliseconds of ``fn`` over ``runs`` calls after one warm-up call."""
    fn()
    t = time.perf_counter()
    for _ in range(runs):
        fn()
    return round((time.perf_counter() - t) / runs * 1000, 2)


def step_pieces(s: collisions.Solve) -> dict[str, float]:
    """Milliseconds of one energy evaluation and its pieces on the sentinel pass's first recull."""
    assert s.prob is not None and s.points is not None and s.exempt is not None and s.knots is not None
    p, ctx, prob = s.params, s.ctx, s.prob
    full = build_terms(ctx, prob, s.points, s.contacts, s.exempt, p, s.scale, p.candidate_slack_m / s.scale, s.allowed,
                       mesh=s.mesh, ground=s.ground)  # fmt: skip
    knots = s.knots.clone().requires_grad_(True)
    terms, rows = solver.recull(ctx, prob, full, knots, p.recull_within_m / s.scale, p.candidate_slack_m / s.scale)

    def backward(total: torch.Tensor | float) -> None:
        assert isinstance(total, torch.Tensor)
        knots.grad = None
        total.backward()

    def fk_rows() -> None:
        mats, gpos = terms.poser.transforms(prob.local(knots), prob.trans)
        xs, ms_ = read_rows(rows, mats)
        backward(sum(x.sum() for x in xs) + sum(m.sum() for m in ms_) + gpos.sum())

    mats = terms.poser.transforms(prob.local(knots), prob.trans)[0].detach().requires_grad_(True)
    return {
        "rows": int(rows.points.weight.shape[0]), "triples": terms.triples.count,
        "energy forward": ms(lambda: solver.energy(ctx, prob, terms, rows, knots, p, s.scale)),
        "energy forward and backward": ms(lambda: backward(solver.energy(ctx, prob, terms, rows, knots, p, s.scale)[0])),
        "kinematics forward and backward": ms(lambda: backward(torch.stack([t.sum() for t in terms.poser.transforms(prob.local(knots), prob.trans)]).sum())),
        "kinematics and rows forward and backward": ms(fk_rows),
        "rows alone forward and backward": ms(lambda: pose_rows(rows.points, mats).sum().backward()),
        "recull": ms(lambda: solver.recull(ctx, prob, full, knots, p.recull_within_m / s.scale, p.candidate_slack_m / s.scale), 3),
    }  # fmt: skip


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--target", default=str(BULKY_SAMPLE), help="the target body (GLB, or builtin:<preset>)")
    add_output(ap, results_dir("bench") / "collision_step_profile.json")
    a = ap.parse_args()
    torch.set_num_threads(2)
    opts = RetargetOptions(fps=a.fps, frame_end=source_frames(a.motion, a.frames, a.fps))
    prepared = prepare(JobInputs(a.motion, a.target, options=opts))
    ctx = refine_context(prepared)
    s = collisions.set_up(ctx, prepared.before, collisions.CollisionParams())
    collisions.set_problem(s)
    pieces = step_pieces(s)
    for k, v in pieces.items():
        print(f"  {k:<42} {v:>10}")
    collisions.resolve(ctx, prepared.before)  # warm
    t = time.perf_counter()
    report = collisions.resolve(ctx, prepared.before).report
    stage = {"seconds": round(time.perf_counter() - t, 3), "iterations": report["iterations"],
             "cpu_timings_s": report["cpu_timings_s"]}  # fmt: skip
    print(f"  stage {stage['seconds']} s, {stage['iterations']} steps, phases (CPU s): {stage['cpu_timings_s']}")
    write_json(a.output, {"motion": a.motion.name, "target": Path(a.target).name, "frames": a.frames,
                          "machine": {**machine(), "torch": torch.__version__}, "step_ms": pieces, "stage": stage})  # fmt: skip


if __name__ == "__main__":
    main()
