"""Floor stage: a body that sinks below the floor is lifted out of it by a root lift of least jerk, planted feet
stay within the judge's float allowance, and a motion above the floor is left alone (a real walk on the bulky
sample, and the lift itself on built depths)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch
from torch import Tensor

from retarget_core.loading import LoadedCharacter, LoadedMotion, load_character, load_motion
from retarget_core.metrics.feet_acceptance import lowest_foot_heights, lowest_vertex_heights
from retarget_core.motion import Motion
from retarget_core.refine import floor

sys.path.insert(0, str(Path(__file__).parent))
from refine_harness import Harness, make_context  # noqa: E402

FLOAT_M = 0.01  # ACCEPTANCE.md: float at most +1 cm
SINK_M = 0.06  # how far the built dip takes the body below the floor (a kneel or a cartwheel's hands)


def test_the_lift_clears_every_frame_with_far_less_jerk_than_following_the_depth() -> None:
    depth = torch.zeros(120, dtype=torch.float64)
    depth[40:52] = 0.05  # ten frames 5 cm under the floor, sharp edges
    ceiling = torch.full_like(depth, math.inf)
    ceiling[:12] = ceiling[100:] = 0.005  # planted feet at both ends
    lift = floor.least_jerk_lift(depth, ceiling, 30.0, floor.FloorParams().size_weight)
    assert bool((lift >= depth).all()) and bool((lift[:12] <= 0.005).all()) and bool((lift[100:] <= 0.005).all())
    assert float(floor.third_difference(lift).abs().max()) < 0.1 * float(floor.third_difference(depth).abs().max())
    assert float(lift[:5].max()) < 0.002  # zero far from the frames it clears


def test_the_lift_does_not_depend_on_the_frame_rate() -> None:
    """The same sink in time, sampled at 30 and at 120 fps, gets the same lift at the shared instants."""
    t30, t120 = torch.arange(90) / 30.0, torch.arange(360) / 120.0

    def sink(t: Tensor) -> Tensor:
        return (0.04 * torch.exp(-(((t - 1.5) / 0.3) ** 2))).double()

    size_weight = floor.FloorParams().size_weight
    a = floor.least_jerk_lift(sink(t30), torch.full((90,), math.inf, dtype=torch.float64), 30.0, size_weight)
    b = floor.least_jerk_lift(sink(t120), torch.full((360,), math.inf, dtype=torch.float64), 120.0, size_weight)
    assert float((a - b[::4]).abs().max()) < 0.003


def test_only_planted_feet_cap_the_lift() -> None:
    """A free foot 5 cm under the floor beside a planted foot on it: the lift may take the planted foot to 1 cm,
    not 6; a planted foot 3 cm under may come up 4 cm; no plant, no cap."""
    planted = torch.tensor([[False, True], [True, False], [False, False]])
    foot = torch.tensor([[-0.05, 0.0], [-0.03, 0.2], [-0.05, -0.05]], dtype=torch.float64)
    ceiling = floor.lift_ceiling(planted, foot, FLOAT_M)
    assert torch.allclose(ceiling[:2], torch.tensor([0.01, 0.04], dtype=torch.float64)) and math.isinf(ceiling[2])


@pytest.fixture(scope="module")
def harness(samples: Path) -> Harness:
    walk: LoadedMotion = load_motion(samples / "motions" / "007_03.bvh")  # a walk, 60 fps
    walk.motion = walk.motion.slice(0, 150)
    bulky: LoadedCharacter = load_character(samples / "characters" / "mh_male_bulky.glb")
    return make_context(walk, bulky, sdf=False)


def _raised(m: Motion, dy: Tensor) -> Motion:
    """``m`` with its root raised by ``dy (F,)`` (m)."""
    trans = m.translations.clone()
    trans[:, m.skeleton.parents.index(-1), 1] += dy.to(trans.dtype)
    return Motion(m.skeleton, m.fps, m.rotations, trans, m.name)


def test_a_sunk_body_is_lifted_out_and_planted_feet_stay_near_the_floor(harness: Harness) -> None:
    ctx = harness.context
    scale = ctx.target.height / 1.80
    f = torch.arange(ctx.num_frames, dtype=torch.float64)
    dip = SINK_M * scale * torch.sin(math.pi * ((f - 60) / 40).clamp(0, 1)).pow(2)  # frames 60-100, smooth
    sunk = _raised(ctx.before, -dip)
    assert float(lowest_vertex_heights(ctx.target, sunk).min()) < -0.04 * scale  # the test is not vacuous
    out = floor.run(ctx, sunk)
    heights = lowest_vertex_heights(ctx.target, out.motion)
    assert float(heights.min()) > -floor.FloorParams().sunk_m * scale, "no vertex below the judge's allowance"
    assert out.report["ground_penetration_cm_after"] < 0.05 * out.report["ground_penetration_cm_before"]
    planted = floor.planted_feet(ctx)
    start = lowest_foot_heights(ctx.target, ctx.target_mapping, sunk)
    feet = lowest_foot_heights(ctx.target, ctx.target_mapping, out.motion)
    allowed = torch.maximum(start, torch.full_like(start, FLOAT_M * scale))
    assert bool(planted.any()) and bool((feet[planted] <= allowed[planted] + 1e-5).all()), "a planted foot floats"
    assert out.report["frames_below_floor"] > 0 and out.report["frames_changed"] >= out.report["frames_below_floor"]
    assert torch.equal(out.motion.rotations, sunk.rotations) and out.report["jerk_share"] == 1.0


def test_a_motion_above_the_floor_is_left_alone(harness: Harness) -> None:
    ctx = harness.context
    up = _raised(ctx.before, torch.full((ctx.num_frames,), 0.05))
    out = floor.run(ctx, up)
    assert out.motion is up and out.report["frames_changed"] == 0
