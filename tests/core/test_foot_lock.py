"""Foot lock: plants held on the floor by two-bone IK (real clips on real bodies), the IK on built cases."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.loading import LoadedCharacter, LoadedMotion, load_character, load_motion
from retarget_core.metrics.feet_acceptance import feet_figures, foot_vertices, lowest_foot_heights
from retarget_core.motion import Motion
from retarget_core.refine import foot_lock
from retarget_core.refine.two_bone_ik import two_bone_ik

sys.path.insert(0, str(Path(__file__).parent))
from refine_harness import Harness, make_context  # noqa: E402

FAST = foot_lock.FootLockParams(check_collisions=False)
MAX_PLANT_MOTION_M = 0.002  # issue 9: "a planted foot moves less than 2 mm while planted"
MAX_JERK_RATIO = 1.1  # ACCEPTANCE.md
MIN_FOOT_ACCURACY = 0.97  # ACCEPTANCE.md


@pytest.fixture(scope="module")
def bulky(samples: Path) -> LoadedCharacter:
    return load_character(samples / "characters" / "mh_male_bulky.glb")


@pytest.fixture(scope="module")
def walk(samples: Path) -> LoadedMotion:
    loaded = load_motion(samples / "motions" / "007_03.bvh")  # a walk, 60 fps
    loaded.motion = loaded.motion.slice(0, 150)
    return loaded


@pytest.fixture(scope="module")
def harness(walk: LoadedMotion, bulky: LoadedCharacter) -> Harness:
    return make_context(walk, bulky, sdf=False)


@pytest.fixture(scope="module")
def locked(harness: Harness) -> foot_lock.StageOutcome:
    return foot_lock.run(harness.context, harness.context.before, FAST)


def _plants(harness: Harness) -> list[tuple[foot_lock.Leg, int, int]]:
    ctx = harness.context
    out = []
    legs = foot_lock.legs_of(ctx)
    for leg, planted in zip(legs, foot_lock.source_plants(ctx, legs, ctx.num_frames), strict=True):
        out += [(leg, a, b) for a, b in foot_lock.plant_spans(planted)]
    return out


def test_planted_foot_holds_still(harness: Harness, locked: foot_lock.StageOutcome) -> None:
    plants = _plants(harness)
    assert len(plants) >= 2, "the walk must have plants for the test to mean anything"
    ctx = harness.context
    scale = ctx.target.height / 1.80
    _, before = ctx.before.global_transforms()
    _, after = locked.motion.global_transforms()
    lowest = lowest_foot_heights(ctx.target, ctx.target_mapping, locked.motion)
    moved_before, ankle_steps = [], []
    for leg, a, b in plants:
        # The toe (the pivot a planted foot rolls on) holds its place to 2 mm over the whole plant...
        toe = after[a : b + 1, leg.toe]
        assert float((toe - toe[0]).norm(dim=-1).max()) < MAX_PLANT_MOTION_M, (leg.side, a, b)
        # ...and the ankle above it only rolls with the heel: less than the judge's 1 cm per 1/30 s.
        ankle = after[a : b + 1, leg.ankle][:, [0, 2]]
        if b > a:
            steps = (ankle[1:] - ankle[:-1]).norm(dim=-1) * (ctx.before.fps / 30.0)
            assert float(steps.max()) < 0.01 * scale
            ankle_steps.append(steps)
        side = 0 if leg.side == "Left" else 1
        floor = lowest[a : b + 1, side]
        assert float(floor.abs().max()) < 0.003 * scale, "a locked foot stands on the floor"
        t0 = before[a : b + 1, leg.toe]
        moved_before.append(float((t0 - t0[0]).norm(dim=-1).max()))
    assert float(torch.cat(ankle_steps).mean()) < MAX_PLANT_MOTION_M
    assert max(moved_before) > MAX_PLANT_MOTION_M, "the copy itself slid: the test is not vacuous"
    assert locked.report["plants_locked"] == len(plants)
    assert locked.report["foot_slide_after_cm_per_frame"]["mean"] < locked.report["foot_slide_before_cm_per_frame"]["mean"]
    assert torch.isfinite(locked.motion.rotations).all() and torch.isfinite(locked.motion.translations).all()


def _leg(bend_z: float = 0.0) -> tuple[torch.Tensor, ...]:
    hip = torch.tensor([[0.0, 1.0, 0.0]])
    knee = torch.tensor([[0.0, 0.55, bend_z]])
    ankle = torch.tensor([[0.0, 0.1, 0.0]])
    return hip, knee, ankle


def _chain(hip: torch.Tensor, knee: torch.Tensor, ankle: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    k = hip + rot.apply(a, knee - hip)
    return k, k + rot.apply(b, ankle - knee)


def test_two_bone_ik_reaches_and_clamps() -> None:
    torch.manual_seed(0)
    n = 64
    hip = torch.zeros(n, 3)
    knee = torch.tensor([0.0, -0.45, 0.1]).expand(n, 3)  # bent: the hip-to-ankle distance is 0.976 of the leg
    ankle = torch.tensor([0.0, -0.9, 0.0]).expand(n, 3)
    ident = rot.identity(n)
    full = float((knee - hip).norm(dim=-1)[0] + (ankle - knee).norm(dim=-1)[0])
    # Reachable targets: random directions, 30..95 % of the leg's length.
    d = torch.nn.functional.normalize(torch.randn(n, 3) + torch.tensor([0.0, -2.0, 0.0]), dim=-1)
    target = d * (full * (0.3 + 0.65 * torch.rand(n, 1)))
    a, b = two_bone_ik(hip, knee, ankle, target, torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), ident, ident)
    _, reached = _chain(hip, knee, ankle, a, b)
    assert float((reached - target).norm(dim=-1).max()) < 1e-5
    # Unreachable: clamped short of full extension along the target's direction, no NaN.
    far = d * full * 1.5
    a, b = two_bone_ik(hip, knee, ankle, far, torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), ident, ident, max_reach=0.99)
    _, got = _chain(hip, knee, ankle, a, b)
    assert torch.isfinite(got).all()
    assert torch.allclose(got.norm(dim=-1), torch.full((n,), 0.99 * full), atol=1e-4)
    assert float((torch.nn.functional.normalize(got, dim=-1) - d).norm(dim=-1).max()) < 1e-4
    # A target at the hip itself: finite.
    a, b = two_bone_ik(hip, knee, ankle, hip.clone(), torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), ident, ident)
    assert torch.isfinite(a).all() and torch.isfinite(b).all()


def test_a_leg_straighter_than_the_clamp_keeps_its_own_extension() -> None:
    """A leg the input holds straighter than ``max_reach`` (0.9997 of its length) is not bent to the clamp: a
    target at its own ankle leaves it as it is, one beyond is reached as far as the leg's own extension (a knee
    bent to the clamp on a few frames of a dance was a jerk; docs/results.md)."""
    hip, knee, ankle = torch.zeros(1, 3), torch.tensor([[0.0, -0.45, 0.011]]), torch.tensor([[0.0, -0.9, 0.0]])
    full = float((knee - hip).norm() + (ankle - knee).norm())
    assert 0.9995 < 0.9 / full < 0.9999
    pole, ident = torch.tensor([[0.0, 0.0, 1.0]]), rot.identity(1)
    a, b = two_bone_ik(hip, knee, ankle, ankle.clone(), pole, ident, ident, max_reach=0.995)
    _, reached = _chain(hip, knee, ankle, a, b)
    assert float((reached - ankle).norm()) < 1e-5
    a, b = two_bone_ik(hip, knee, ankle, torch.tensor([[0.0, -1.2, 0.0]]), pole, ident, ident, max_reach=0.995)
    _, reached = _chain(hip, knee, ankle, a, b)
    assert float(reached.norm()) == pytest.approx(0.9, abs=1e-5)


@pytest.mark.parametrize("pole_z", [1.0, -1.0])
def test_knee_bends_toward_its_pole(pole_z: float) -> None:
    hip, knee, ankle = _leg(0.0)  # a straight leg: the bending plane comes from the pole alone
    target = torch.tensor([[0.0, 0.4, 0.0]])  # closer: the knee must bend
    pole = torch.tensor([[0.0, 0.0, pole_z]])
    a, b = two_bone_ik(hip, knee, ankle, target, pole, rot.identity(1), rot.identity(1))
    k, reached = _chain(hip, knee, ankle, a, b)
    assert float((reached - target).norm()) < 1e-5
    assert float(k[0, 2]) * pole_z > 0.1, f"knee at {k.tolist()} does not point to the pole"


def test_clip_without_plants_is_unchanged(harness: Harness) -> None:
    ctx = harness.context
    saved, saved_planted = ctx.feet, ctx.planted
    ctx.feet = FootContacts(torch.zeros_like(saved.labels), saved.joints)
    ctx.planted = None if saved_planted is None else torch.zeros_like(saved_planted)
    try:
        out = foot_lock.run(ctx, ctx.before, FAST)
    finally:
        ctx.feet, ctx.planted = saved, saved_planted
    assert out.motion is ctx.before or (
        torch.equal(out.motion.rotations, ctx.before.rotations) and torch.equal(out.motion.translations, ctx.before.translations)
    )
    assert out.report["frames_changed"] == 0 and out.report["plants_locked"] == 0
    assert out.report["feet_lifted_frames"] == 0


def test_the_report_counts_the_frames_a_free_foot_was_raised() -> None:
    """A reviewer sees how often and how far free feet were raised (over the floor, or to the source's toe
    height): frames where either foot rose, and the largest raise."""
    lift_cm = torch.zeros(6, 2)
    lift_cm[1, 0], lift_cm[2, 1], lift_cm[3, 0], lift_cm[3, 1] = 0.5, 2.0, 1.0, 0.0001
    report = foot_lock._report(6, [1, 1], None, None, 0, 0.0, None, None, 0.0, 0.0, lift_cm)
    assert report["feet_lifted_frames"] == 3 and report["feet_max_lift_cm"] == 2.0


def _jerk(motion: Motion, height: float) -> float:
    _, p = motion.global_transforms()
    p = p * (1.80 / height)
    return float((p[3:] - 3 * p[2:-1] + 3 * p[1:-2] - p[:-3]).norm(dim=-1).mean())


def test_jerk_ratio_on_a_walk(harness: Harness, locked: foot_lock.StageOutcome) -> None:
    ctx = harness.context
    source = _jerk(harness.source_view, ctx.source_body.height)
    after = _jerk(locked.motion, ctx.target.height)
    assert after / source <= MAX_JERK_RATIO, (after / source, _jerk(ctx.before, ctx.target.height) / source)


def test_pelvis_lowered_only_where_needed(harness: Harness, locked: foot_lock.StageOutcome) -> None:
    assert locked.report["pelvis_max_drop_cm"] < 5.0
    assert locked.report["feet_lifted_frames"] <= locked.report["frames_changed"]
    feet = foot_vertices(harness.context.target, harness.context.target_mapping)
    assert len(feet.left) > 100 and len(feet.right) > 100


@pytest.mark.slow
def test_leg_collisions_rechecked(walk: LoadedMotion, bulky: LoadedCharacter) -> None:
    h = make_context(walk, bulky)
    out = foot_lock.run(h.context, h.context.before)
    for key in ("leg_penetration_before", "leg_penetration_after"):
        pen = out.report[key]
        assert pen is not None and pen["frames"] == out.report["frames_changed"]
        assert pen["max_depth_cm"] >= 0.0


def test_lock_lowers_the_skate_on_a_walk(harness: Harness, locked: foot_lock.StageOutcome) -> None:
    """The plants locked are the judge's (ctx.planted): planted feet slide less than the copy's."""
    ctx = harness.context
    assert ctx.planted is not None and bool(ctx.planted.any())
    before = feet_figures(ctx.target, ctx.target_mapping, ctx.before, ctx.planted)
    after = feet_figures(ctx.target, ctx.target_mapping, locked.motion, ctx.planted)
    assert after.skate_cm is not None and before.skate_cm is not None and after.skate_cm < before.skate_cm


def test_judged_foot_accuracy_on_a_walk(harness: Harness, locked: foot_lock.StageOutcome) -> None:
    """The result's plant labels agree with the source's as the judge reads them (0.937 before the free foot
    kept the source's toe height: the lock's fades pulled a hovering, still foot under the judge's 3 cm line)."""
    ctx = harness.context
    before = feet_figures(ctx.target, ctx.target_mapping, ctx.before, ctx.planted)
    after = feet_figures(ctx.target, ctx.target_mapping, locked.motion, ctx.planted)
    assert after.foot_accuracy >= MIN_FOOT_ACCURACY, (before.as_dict(), after.as_dict())


def test_lock_does_not_lower_foot_accuracy_on_a_walk(harness: Harness, locked: foot_lock.StageOutcome) -> None:
    ctx = harness.context
    before = feet_figures(ctx.target, ctx.target_mapping, ctx.before, ctx.planted)
    after = feet_figures(ctx.target, ctx.target_mapping, locked.motion, ctx.planted)
    assert after.foot_accuracy >= before.foot_accuracy, (before.as_dict(), after.as_dict())


def test_floor_lift_rises_from_the_plant_edge_without_a_step() -> None:
    """A foot that leaves a plant and sinks 1 cm a frame into the floor: the lift is 0 in the plant, never below
    the depth, and rises at most twice as fast as the depth (spreading the later depth back to the plant's edge
    raised the foot 3-4 cm in one frame there: the knee jerk of issue 22 item 4)."""
    frames, blend = 30, 4
    leg = foot_lock.Leg("Left", 0, 1, 2, -1, 0, 1)
    model = foot_lock.FootModel(torch.tensor([[0.0, -0.1, 0.0]]), torch.zeros(1, dtype=torch.bool))
    f = torch.arange(frames)
    inside = (f >= 5) & (f <= 12)
    sink = (0.01 * (f - 12)).clamp(0.0, 0.06)  # 0 in and before the plant, then 1 cm a frame down to 6 cm
    target = torch.zeros(frames, 3)
    target[:, 1] = 0.1 - sink  # the ankle 10 cm above its foot's sole
    plan = foot_lock.LegPlan(target, rot.identity(frames), None, (f >= 1) & (f <= 20), inside)
    drop = torch.zeros(frames)
    lift = foot_lock.floor_lift(leg, plan, model, drop, torch.zeros(3, 3), blend)
    solved = plan.driven & ~inside
    assert bool((lift[inside] == 0).all())
    assert bool((lift[solved] >= sink[solved] - 1e-7).all())
    assert float(lift.diff().abs().max()) <= 2.0 * float(sink.diff().abs().max())  # before: 4.7 cm in one frame


def test_a_free_foot_the_copy_dips_under_the_floor_is_lifted() -> None:
    """A foot that slides along the floor, unplanted (a dance: it moves more than 1 cm a frame), and that the copy
    sinks up to 3 cm under it, far from any plant, with no body lift given (``body_floor_lift`` gives none beside
    a planted foot): lifted at least to the floor where it sinks (the judge's ground penetration, issue 22), not
    elsewhere."""
    frames, blend = 60, 4
    leg = foot_lock.Leg("Left", 0, 1, 2, -1, 0, 1)
    model = foot_lock.FootModel(torch.tensor([[0.0, -0.1, 0.0]]), torch.zeros(1, dtype=torch.bool))
    f = torch.arange(frames)
    sink = (0.03 * torch.sin((f - 25).clamp(0, 20) * torch.pi / 20)).clamp_min(0.0)  # frames 26-44
    target = torch.zeros(frames, 3)
    target[:, 1] = 0.1 - sink
    none = torch.zeros(frames, dtype=torch.bool)
    plan = foot_lock.LegPlan(target, rot.identity(frames), None, none, f < 4)  # a plant at the start only
    lift = foot_lock.floor_lift(leg, plan, model, torch.zeros(frames), torch.zeros(3, 3), blend)
    assert bool((lift >= sink - 1e-7).all()) and float(sink.max()) > 0.029
    assert bool((lift[: 26 - 2 * blend] == 0).all()) and bool((lift[45 + 2 * blend :] == 0).all())  # its spread


def test_a_free_foot_keeps_the_source_toe_height_and_leaves_its_plant_smoothly() -> None:
    """A foot the source lifts 5 cm off the floor right after a plant, that the input carries only 1 cm up (a
    hovering foot the judge would call planted): lifted to the source's toe height away from the plant, not
    in the plant, and rising from the plant's edge at most twice as fast as the shortfall does (as the floor
    lift above)."""
    frames, blend = 40, 4
    leg = foot_lock.Leg("Left", 0, 1, 2, -1, 0, 1)
    model = foot_lock.FootModel(torch.tensor([[0.0, -0.1, 0.0]]), torch.zeros(1, dtype=torch.bool))
    f = torch.arange(frames)
    inside = f <= 10
    source_toe = (0.01 * (f - 10)).clamp(0.0, 0.05)  # the source's toe leaves the floor at 1 cm a frame
    target = torch.zeros(frames, 3)
    target[:, 1] = 0.1 + (0.002 * (f - 10)).clamp(0.0, 0.01)  # the input's ankle: 1 cm up at most
    plan = foot_lock.LegPlan(target, rot.identity(frames), None, inside.clone(), inside)
    least = 0.1 + source_toe  # the ankle stands 10 cm above the floor at rest
    lift = foot_lock.floor_lift(leg, plan, model, torch.zeros(frames), torch.zeros(3, 3), blend, least)
    raised = target[:, 1] + lift
    away = f > 10 + blend
    assert bool((lift[inside] == 0).all())
    assert bool((raised[away] >= least[away] - 1e-7).all())
    shortfall = (least - target[:, 1]).clamp_min(0.0)
    assert float(lift.diff().abs().max()) <= 2.0 * float(shortfall.diff().abs().max())


def test_a_free_toe_is_kept_up_to_just_over_the_plant_line() -> None:
    """The least toe height follows the source's toe above its rest height (scaled to the body) up to 5 mm over
    the judge's 3 cm plant line: the least lift that keeps a free foot free."""
    legs = [foot_lock.Leg("Left", 0, 1, 2, 3, 0, 1), foot_lock.Leg("Right", 4, 5, 6, -1, 2, 3)]
    rest = torch.zeros(7, 3)
    rest[3, 1], rest[6, 1] = 0.02, 0.08  # the left toe and the right ankle (no toe) at rest
    source = torch.tensor([[0.0, 0.01], [0.02, 0.034], [0.06, 0.2]])  # (F, 2) at 1.80 m
    ctx = SimpleNamespace(toe_heights=source)
    params = foot_lock.FootLockParams()
    left, right = foot_lock.least_toe_heights(ctx, legs, rest, 0.5, 3, params)  # type: ignore[arg-type]
    torch.testing.assert_close(left, torch.tensor([0.02, 0.03, 0.02 + 0.5 * params.free_toe_height_m]))
    torch.testing.assert_close(right, torch.tensor([0.085, 0.097, 0.08 + 0.5 * params.free_toe_height_m]))
    assert foot_lock.least_toe_heights(SimpleNamespace(toe_heights=None), legs, rest, 0.5, 3, params) == [None, None]  # type: ignore[arg-type]


def _dipping_legs(frames: int, left_inside: torch.Tensor, sink: torch.Tensor) -> tuple[list, list, list]:
    """Two legs without toes, ankles 10 cm above their soles: the left standing on the floor (planted on
    ``left_inside (F,)``), the right free and sunk ``sink (F,)`` m under the floor."""
    legs = [foot_lock.Leg("Left", 0, 1, 2, -1, 0, 1), foot_lock.Leg("Right", 3, 4, 5, -1, 2, 3)]
    model = foot_lock.FootModel(torch.tensor([[0.0, -0.1, 0.0]]), torch.zeros(1, dtype=torch.bool))
    left, right = torch.zeros(frames, 3), torch.zeros(frames, 3)
    left[:, 1], right[:, 1] = 0.1, 0.1 - sink
    none = torch.zeros(frames, dtype=torch.bool)
    plans = [foot_lock.LegPlan(left, rot.identity(frames), None, left_inside.clone(), left_inside),
             foot_lock.LegPlan(right, rot.identity(frames), None, none, none.clone())]  # fmt: skip
    return legs, plans, [model, model]


def test_the_body_rises_where_no_foot_is_planted_and_the_legs_lift_the_rest() -> None:
    """A dancer's free foot that the copy sinks 4 cm under the floor (the source's own floor, issue 22's dance):
    where neither foot is planted the whole body rises, which moves no foot against the hips (the judged
    end-effector error; bending the leg up moved the foot 6 cm from the source's on the heaviest body), so the
    leg is not lifted there; where the other foot stands planted the body stays down and the leg lifts. Foot
    under the floor nowhere: body plus leg cover the depth on every frame, and the body rises no higher than
    the dip asks."""
    frames, blend, scale = 90, 4, 1.0
    f = torch.arange(frames)
    sink = (0.04 * torch.sin((f - 20).clamp(0, 50) * torch.pi / 50)).clamp_min(0.0)  # frames 21-69
    left_inside = (f < 4) | ((f >= 60) & (f <= 75))  # the left foot planted at the start and late in the dip
    legs, plans, models = _dipping_legs(frames, left_inside, sink)
    params = foot_lock.FootLockParams()
    body = foot_lock.body_floor_lift(legs, plans, models, torch.zeros(6, 3), scale, 30.0, params)
    lift = foot_lock.floor_lift(legs[1], plans[1], models[1], torch.zeros(frames), torch.zeros(6, 3), blend, None, body)
    assert bool((body[left_inside] == 0).all())
    assert bool((body + lift >= sink - 1e-7).all())
    assert float(body.max()) <= 1.25 * float(sink.max())  # no bump over the dip (18 cm without the fade)
    free = (f >= 35) & (f <= 42)  # deep, and far from the left foot's plants
    assert float(sink[free].min()) > 0.03
    assert bool((lift[free] == 0).all())
    assert bool((lift[left_inside] >= sink[left_inside] - 1e-7).all())  # planted beside it: the leg lifts
