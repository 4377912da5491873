"""Probe for the ground-penetration target: one clip x body through the default chain, then the root raised by a
smooth upper envelope of the lowest vertex's depth below y = 0 (each sunk frame's depth, fading over ``ramp``
frames on either side), for a few ramps, and by the floor stage (:mod:`retarget_core.refine.floor`: a lift of
least jerk, the method's way); the judge's figures printed for each. The chain here runs without its floor stage.

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/diag/floor_probe.py \\
        ../shared/data/motions/cmu_hard/131_01.bvh ~/.cache/retarget/heldout/hard_heaviest-8fa5de322a2a.glb
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import Tensor

from retarget_core.metrics.acceptance import figures_from_measures, measure_acceptance
from retarget_core.metrics.feet_acceptance import lowest_vertex_heights
from retarget_core.motion import Motion
from retarget_core.pipeline import refine_context
from retarget_core.refine import floor, refinement_stages
from retarget_core.refine.temporal import fallback_weights

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case  # noqa: E402

FIGURES = ("pen_percent", "contact_preservation", "foot_accuracy", "float_cm", "ground_penetration_cm",
           "end_effector_error_cm", "jerk_ratio")  # fmt: skip
RAMPS = (4, 8, 16)  # frames at 30 fps


def lift_envelope(depth: Tensor, ramp: int) -> Tensor:
    """``(F,)`` root lift: at least ``depth (F,)`` (m, >= 0) on every frame, fading to 0 over ``ramp`` frames (the
    never-worse blend's envelope, :func:`fallback_weights`, on caps ``1 - depth / max depth``)."""
    deepest = float(depth.max()) if len(depth) else 0.0
    if deepest <= 0.0:
        return torch.zeros_like(depth)
    return deepest * (1.0 - fallback_weights(1.0 - depth / deepest, ramp).to(depth.dtype))


def main() -> None:
    a = case_parser(__doc__, frames=300).parse_args()
    torch.set_num_threads(1)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    prepared, source = case.prepared, case.source
    ctx, target = refine_context(prepared), prepared.target
    motion = prepared.before
    for info, stage in refinement_stages():
        if stage is not None and info.name != "floor" and prepared.inputs.options.stages.enabled(info.name):
            motion = stage(ctx, motion).motion

    def show(name: str, m: Motion) -> None:
        f = figures_from_measures(measure_acceptance(target.character, target.mapping, m), source)
        print(f"{name:>10}: " + "  ".join(f"{k} {getattr(f, k):.4g}" for k in FIGURES), flush=True)

    show("no floor", motion)
    depth = (-lowest_vertex_heights(target.character, motion)).clamp_min(0.0)
    root = motion.skeleton.parents.index(-1)
    for ramp in RAMPS:
        trans = motion.translations.clone()
        trans[:, root, 1] += lift_envelope(depth, ramp).to(trans.dtype)
        show(f"lift r{ramp}", Motion(motion.skeleton, motion.fps, motion.rotations, trans, motion.name))
    show("floor", floor.run(ctx, motion).motion)


if __name__ == "__main__":
    main()
