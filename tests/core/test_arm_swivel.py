"""The elbow swivel stage on a real body (the skinny sample) with built poses, measured as the judge measures
(:func:`retarget_core.metrics.acceptance.measure_pose`): an arm whose elbow is swung into the torso while its
hand rests in front of the belly is turned back out, with the wrist and the hand's world rotation where they
were and the other arm untouched; the swivel itself turns the elbow about the shoulder-to-wrist line only."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.loading import load_character
from retarget_core.metrics.acceptance import measure_pose
from retarget_core.metrics.acceptance_body import PARTS, acceptance_body
from retarget_core.motion import Motion
from retarget_core.refine import arm_swivel
from retarget_core.refine.arms import Arm, about_axis, arms_of, swivel_arms
from retarget_core.refine.hand_contacts import apply_moves
from retarget_core.refine.judged_check import ArmFigures
from retarget_core.refine.temporal import least_cost_path, smoothstep
from tests.core.test_hand_contacts import FRAMES, LEFT, _context, _rest

TURN_IN_DEG = -30.0  # on the skinny sample this swings the left elbow about 4 cm into the torso


@pytest.fixture(scope="module")
def skinny(samples: Path) -> tuple[Character, JointMapping]:
    loaded = load_character(samples / "characters" / "mh_female_skinny.glb")
    return loaded.character, loaded.mapping


def _hand_on_belly(ch: Character, mapping: JointMapping) -> Motion:
    """The rest pose with the left wrist 16 cm in front of the belly, 12 cm above the hips (elbow clear)."""
    rest = _rest(ch)
    _, gpos = rest.global_transforms()
    wrist = gpos[0, mapping.joints["LeftHand"]].double()
    hips = gpos[0, mapping.joints["Hips"]].double()
    goal = torch.tensor([0.06 * ch.height / 1.7, float(hips[1]) + 0.12, 0.16], dtype=torch.float64)
    moves = torch.zeros(FRAMES, 2, 3, dtype=torch.float64)
    moves[:, LEFT] = goal - wrist
    return apply_moves(rest, arms_of(mapping, ch.skeleton.parents), moves, 0.995)


def _left_arm_depth(ch: Character, mapping: JointMapping, motion: Motion, frames: list[int]) -> np.ndarray:
    """``(n,)`` the judge's deepest counted left-arm vertex (m) at ``frames``."""
    arm = acceptance_body(ch, mapping).part_of_vertex == PARTS.index("left_arm")
    grot, gpos = motion.global_transforms()
    with torch.no_grad():
        posed = ch.pose_vertices(grot[frames], gpos[frames]).double().numpy()
    return np.array([measure_pose(ch, mapping, p).depth[arm].max() for p in posed])


def test_an_elbow_swung_into_the_torso_is_turned_out_with_the_hand_kept(skinny) -> None:  # type: ignore[no-untyped-def]
    ch, mapping = skinny
    clear = _hand_on_belly(ch, mapping)
    assert _left_arm_depth(ch, mapping, clear, [0])[0] == 0.0
    t = torch.arange(FRAMES, dtype=torch.float64)
    ease = torch.minimum(smoothstep((t - 5.0) / 5.0), smoothstep((34.0 - t) / 5.0))
    angles = torch.zeros(FRAMES, 2, dtype=torch.float64)
    angles[:, LEFT] = math.radians(TURN_IN_DEG) * ease
    target = swivel_arms(clear, arms_of(mapping, ch.skeleton.parents), angles)
    assert (_left_arm_depth(ch, mapping, target, list(range(12, 28, 3))) > 0.02).all()  # deep, as the judge reads it

    out = arm_swivel.run(_context(ch, mapping, target, target), target)
    after = _left_arm_depth(ch, mapping, out.motion, list(range(12, 28, 3)))
    assert (after < 0.01).all(), after  # no frame deeper than 1 cm left on the span
    grot_in, gpos_in = target.global_transforms()
    grot_out, gpos_out = out.motion.global_transforms()
    hand = mapping.joints["LeftHand"]
    assert float((gpos_out[:, hand] - gpos_in[:, hand]).norm(dim=-1).max()) < 1e-5  # the wrist stays
    assert float((rot.mul(rot.inv(grot_in[:, hand]), grot_out[:, hand])[:, :3]).norm(dim=-1).max()) < 1e-5
    right = [mapping.joints[n] for n in ("RightArm", "RightForeArm", "RightHand")]
    assert torch.equal(out.motion.rotations[:, right], target.rotations[:, right])
    assert out.report["frames_changed"] > 0 and out.report["frames_arm_deeper_1cm_before"] > 0


def test_the_swivel_turns_the_elbow_about_the_shoulder_wrist_line(skinny) -> None:  # type: ignore[no-untyped-def]
    ch, mapping = skinny
    motion = _hand_on_belly(ch, mapping)
    arms = arms_of(mapping, ch.skeleton.parents)
    angles = torch.zeros(FRAMES, 2, dtype=torch.float64)
    angles[:, LEFT] = math.radians(25.0)
    out = swivel_arms(motion, arms, angles)
    _, before = motion.global_transforms()
    _, after = out.global_transforms()
    a, b, c = (mapping.joints[n] for n in ("LeftArm", "LeftForeArm", "LeftHand"))
    axis = (before[:, c] - before[:, a]) / (before[:, c] - before[:, a]).norm(dim=-1, keepdim=True)
    expected = before[:, a] + rot.apply(about_axis(axis, torch.full((FRAMES,), math.radians(25.0))), before[:, b] - before[:, a])
    assert float((after[:, b] - expected).norm(dim=-1).max()) < 1e-5  # the elbow on its circle about the line
    assert float((after[:, c] - before[:, c]).norm(dim=-1).max()) < 1e-5
    untouched = swivel_arms(motion, arms, torch.zeros(FRAMES, 2, dtype=torch.float64))
    assert torch.equal(untouched.rotations, motion.rotations)


def test_the_least_cost_path_is_the_best_of_all_paths() -> None:
    gen = torch.Generator().manual_seed(3)
    cost = torch.rand(5, 3, generator=gen, dtype=torch.float64)
    cost[2, 1] = math.inf  # a level not measured on a frame is never chosen there
    levels = torch.tensor([0.0, -0.5, 0.6], dtype=torch.float64)

    def total(path: tuple[int, ...]) -> float:
        steps = sum(0.3 * float(levels[a] - levels[b]) ** 2 for a, b in zip(path, path[1:], strict=False))
        return sum(float(cost[f, k]) for f, k in enumerate(path)) + steps

    best = min(itertools.product(range(3), repeat=5), key=total)
    assert tuple(least_cost_path(cost, levels, 0.3).tolist()) == best


def test_the_swivel_keeps_one_way_round_rather_than_flip_for_a_millimetre() -> None:
    """An elbow 2 cm in the body on frames 5..24: turned 35 degrees one way it is 2 mm deep; the other way is 1 mm
    better on one frame only. The path turns one way over the span and eases back, never flipping."""
    f_n, turn = 30, math.radians(35.0)
    depth = torch.full((f_n, 2, 3), math.inf, dtype=torch.float64)
    depth[:, :, 0] = 0.0
    depth[5:25, :, 0] = 0.02
    depth[2:28, :, 1:] = 0.003
    depth[5:25, :, 2] = 0.002
    depth[15, :, 1] = 0.001
    levels = torch.tensor([0.0, -turn, turn], dtype=torch.float64)
    table = arm_swivel.TurnTable(levels, depth, torch.zeros_like(depth), depth[:, :, 0] > 0, depth[:, :, 0] > 0.01,
                                 torch.zeros(f_n, 2, dtype=torch.bool))  # fmt: skip
    arm = Arm(upper=1, fore=2, hand=3, side=0, followers=())
    p = arm_swivel.SwivelParams(smooth_seconds=0.0)
    turned = arm_swivel.coherent_turns(table, torch.isfinite(depth), [arm], p, 30.0, 1.0)[:, arm.side]
    assert torch.allclose(turned[5:25], torch.full((20,), turn, dtype=torch.float64))
    assert float(turned.min()) >= 0.0 and float(turned[:2].abs().max()) == 0.0 and float(turned[28:].abs().max()) == 0.0


def test_the_search_reads_the_arms_own_points_and_the_check_the_legs_in_it_too(skinny) -> None:  # type: ignore[no-untyped-def]
    """A hand pressed 3 cm into its thigh: the judge's arm penetration (the never-worse check's) reads the
    thigh's points inside the hand; the swivel's search reads the arm's own points without the hand (a swivel
    keeps the hand) and the thigh's points inside the arm where it is told to (where they were before the turn),
    the same from one search as alone."""
    from retarget_core.contacts.arm_depth import (
        _figures,
        _hits,
        arm_penetration,
        arm_penetration_and_search,
        arm_search_figures,
    )
    from retarget_core.contacts.hand_reach import PosedParts, posed_for_reach, reach_body
    from tests.core.test_hand_contacts import _hanging, _lifted, _placed

    ch, mapping = skinny
    rb = reach_body(ch, mapping)
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    pressed = _lifted(source, mapping, LEFT, torch.tensor([-side * 0.03, 0.0, 0.0], dtype=torch.float64))
    frames = torch.arange(12, 28, 4)
    pp = PosedParts(rb, posed_for_reach(rb, ch, pressed, frames))
    cap = 0.08 * rb.scale
    count, deepest, _ = arm_penetration(pp, LEFT, cap)
    (_, deepest_both, _), (search_both, volume_both, legs_in) = arm_penetration_and_search(pp, LEFT, cap)
    search, volume = arm_search_figures(pp, LEFT, cap, legs_in)
    own, own_volume = arm_search_figures(pp, LEFT, cap, torch.zeros(len(frames), dtype=torch.bool))
    own_count = _figures(len(frames), _hits(pp, LEFT, len(rb.arm_points[LEFT]), cap, with_legs=False))[0]
    assert (deepest > 0.01).all() and (count > own_count).all()  # the hand in the thigh, the thigh in the hand
    assert torch.equal(deepest, deepest_both) and torch.equal(search, search_both) and torch.equal(volume, volume_both)
    assert legs_in.all() and (own > 0).all() and (own <= search).all()  # the wrist's cells are in the thigh too
    assert (own_volume < volume).all()  # the thigh's points in the hand are read only where told


def test_the_path_takes_only_turns_the_never_worse_check_would_keep() -> None:
    """A turn that brings the deepest point up but grows the arm's penetration volume beyond the check's allowance
    (or leaves a point deeper than the frame's deepest by more than its limit) is not on the path: the check
    would withdraw it, and the withdrawal's blend spreads to its neighbours."""
    f_n, turn = 10, 0.6
    depth = torch.full((f_n, 2, 2), 0.02, dtype=torch.float64)
    depth[:, :, 1] = 0.005
    volume = torch.full((f_n, 2, 2), 1e-6, dtype=torch.float64)
    volume[5:, :, 1] = 5e-6  # frames 5-9: the turn's points fill four times the volume
    table = arm_swivel.TurnTable(torch.tensor([0.0, turn], dtype=torch.float64), depth, volume, depth[:, :, 0] > 0,
                                 depth[:, :, 0] > 0.01, torch.zeros(f_n, 2, dtype=torch.bool))  # fmt: skip
    before = ArmFigures(torch.full((f_n,), 2e-6), torch.full((f_n,), 0.02), torch.full((f_n,), 10.0))
    accepted = arm_swivel.accepted_turns(table, before, 1.0)
    assert accepted[:5, :, 1].all() and not accepted[5:, :, 1].any() and accepted[:, :, 0].all()
    deeper = table.depth.clone()
    deeper[:, :, 1] = 0.0225  # 2.5 mm deeper than the frame's deepest (the limit: 2)
    assert not arm_swivel.accepted_turns(replace(table, depth=deeper), before, 1.0)[:, :, 1].any()
    arm = Arm(upper=1, fore=2, hand=3, side=0, followers=())
    p = arm_swivel.SwivelParams(smooth_seconds=0.0)
    turned = arm_swivel.coherent_turns(table, accepted, [arm], p, 30.0, 1.0)[:, arm.side]
    assert torch.equal(turned, torch.tensor([turn] * 5 + [0.0] * 5, dtype=torch.float64))


def test_a_smoothed_turn_found_worse_eases_back_to_the_paths_turn_before_any_withdrawal(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The smoothing puts unmeasured turns between the path's measured ones; where the check finds one worse the
    frame goes back to the path's own turn (measured, accepted), and only a frame still worse loses its turn."""
    from types import SimpleNamespace

    f_n = 30
    path = torch.zeros(f_n, 2, dtype=torch.float64)
    path[8:22, 0] = 0.6
    calls: list[torch.Tensor] = []

    def check(ctx, rb, motion, moved, changed, before):  # type: ignore[no-untyped-def]
        calls.append(changed)
        weight = torch.ones(f_n, dtype=torch.float64)
        weight[[7, 8] if len(calls) == 1 else [7]] = 0.0  # first the smoothing's edge, then the frame before it
        return weight

    monkeypatch.setattr(arm_swivel, "never_worse_weights", check)
    ctx = SimpleNamespace(target=SimpleNamespace(num_vertices=100))
    motion = SimpleNamespace(num_frames=f_n, fps=30.0)
    p = arm_swivel.SwivelParams()
    turned, eased, share = arm_swivel.checked_turns(ctx, None, motion, [], path, ArmFigures.zeros(f_n), p)
    smooth = arm_swivel.weighted_smooth(path, torch.ones(f_n, dtype=torch.float64), p.smooth_seconds * 30.0)
    assert float(turned[8, 0]) == 0.6 and float(turned[7, 0]) == 0.0  # eased to the path: 0.6 on 8, 0 on 7
    assert torch.equal(turned[10:20], smooth[10:20]) and float(smooth[7, 0]) > 0.0
    assert int((eased < 1).sum()) == 2 and int((share < 1).sum()) == 1
    assert len(calls) == 2 and calls[1].tolist() == [8]  # only the eased frame still turned is checked again
