"""The hand contact stage on a real body (the skinny sample) with built poses, measured as the judge measures
(:func:`retarget_core.metrics.acceptance.measure_pose`): a hand that rests on its thigh in the source and is
lifted 5 cm off it on the target is put back on it; one pressed 2.5 cm into it is moved out to its surface, over a
span or for a few frames; a hand clear of the body in the source that the target
brings within a centimetre of the torso is moved clear of it; an arm with nothing to keep or avoid keeps its
rotations bit for bit; the moves' smoothing in time follows the wanted moves where they are defined and never overshoots them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor

from retarget_core.body_parts import body_parts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import no_contacts
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.contacts.hand_depth import HandDepth, hand_depths
from retarget_core.contacts.hand_reach import PosedParts, ReachBody, hand_reach, posed_for_reach, reach_body
from retarget_core.contacts.part_axes import away_from_bones
from retarget_core.contacts.self_contact import SelfContacts
from retarget_core.context import RefineContext
from retarget_core.loading import load_character
from retarget_core.metrics.acceptance import measure_pose
from retarget_core.metrics.acceptance_body import CONTACT_PARTS, PARTS
from retarget_core.motion import Motion
from retarget_core.refine import hand_contacts
from retarget_core.refine.arms import arms_of
from retarget_core.refine.hand_contacts import apply_moves
from retarget_core.refine.temporal import smoothstep, weighted_smooth

FRAMES = 40
LEFT, RIGHT = 0, 1


@pytest.fixture(scope="module")
def skinny(samples: Path) -> tuple[Character, JointMapping, ReachBody]:
    loaded = load_character(samples / "characters" / "mh_female_skinny.glb")
    return loaded.character, loaded.mapping, reach_body(loaded.character, loaded.mapping)


def _rest(ch: Character) -> Motion:
    sk = ch.skeleton
    return Motion(sk, 30.0, sk.rest_rotations.expand(FRAMES, -1, -1).clone(),
                  sk.rest_translations.expand(FRAMES, -1, -1).clone(), "rest")  # fmt: skip


def _hanging(ch: Character, mapping: JointMapping, rb: ReachBody) -> Motion:
    """The rest pose with the left wrist 7 cm outside the left thigh's outer side at half the body's height."""
    rest = _rest(ch)
    _, gpos = rest.global_transforms()
    wrist = gpos[0, mapping.joints["LeftHand"]].double()
    v = ch.vertices.double()
    leg = torch.from_numpy(np.nonzero(rb.body.part_of_vertex == PARTS.index("left_leg"))[0])
    level = leg[(v[leg, 1] - 0.5 * ch.height).abs() < 0.02]
    side = torch.sign(wrist[0])
    outer = v[level[(v[level, 0] * side).argmax()]]
    moves = torch.zeros(FRAMES, 2, 3, dtype=torch.float64)
    moves[:, LEFT] = outer + torch.tensor([float(side) * 0.07, 0.0, 0.0], dtype=torch.float64) - wrist
    return apply_moves(rest, arms_of(mapping, ch.skeleton.parents), moves, 0.995)


def _placed(ch: Character, mapping: JointMapping, rb: ReachBody, motion: Motion, side: int, part: str,
            clearance: float) -> Motion:  # fmt: skip
    """``motion`` with hand ``side``'s wrist moved so the hand's nearest sampled point lies ``clearance`` (m) from
    ``part`` on every frame (read on frame 0: the motion holds one pose)."""
    posed = posed_for_reach(rb, ch, motion, torch.tensor([0]))
    r = hand_reach(rb, posed, torch.tensor([0]), torch.tensor([side]), torch.tensor([PARTS.index(part)]),
                   torch.tensor([1.0]))  # fmt: skip
    gap = (r.surface_point - r.hand_point)[0]
    move = gap * (1.0 - clearance / float(r.distance[0]))
    moves = torch.zeros(FRAMES, 2, 3, dtype=torch.float64)
    moves[:, side] = move
    return apply_moves(motion, arms_of(mapping, ch.skeleton.parents), moves, 0.995)


def _context(ch: Character, mapping: JointMapping, source: Motion, target: Motion) -> RefineContext:
    e = torch.zeros(0, dtype=torch.long)
    parts = body_parts(ch, mapping)
    contacts = SelfContacts(FRAMES, parts.names, e, e, e, torch.zeros(0, 3, 2, dtype=torch.long), torch.zeros(0, 3),
                            torch.zeros(0, dtype=torch.bool), torch.zeros(0))  # fmt: skip
    return RefineContext(
        target=ch, target_mapping=mapping, parts=parts, sdf=None, source_body=ch,  # type: ignore[arg-type]
        source_mapping=mapping, source_view=source, self_contacts=contacts, constraints=no_contacts(FRAMES),
        feet=FootContacts(torch.zeros(FRAMES, 4, dtype=torch.bool), [-1] * 4), before=target,
    )  # fmt: skip


def _judged(ch: Character, mapping: JointMapping, motion: Motion, frames: list[int]) -> np.ndarray:
    """``(n, 2, 4)`` the judge's hand distances (m) at ``frames``."""
    grot, gpos = motion.global_transforms()
    with torch.no_grad():
        posed = ch.pose_vertices(grot[frames], gpos[frames]).double().numpy()
    return np.stack([measure_pose(ch, mapping, p).hand_distance for p in posed])


def _lifted(motion: Motion, mapping: JointMapping, side: int, offset: Tensor) -> Motion:
    """``motion`` with hand ``side`` moved by ``offset (3,)`` on frames 10-29, eased in over 5-10 and out over
    29-34 (the frames before 5 and after 34 unchanged)."""
    t = torch.arange(FRAMES, dtype=torch.float64)
    ease = torch.minimum(smoothstep((t - 5.0) / 5.0), smoothstep((34.0 - t) / 5.0))
    moves = torch.zeros(FRAMES, 2, 3, dtype=torch.float64)
    moves[:, side] = ease[:, None] * offset
    return apply_moves(motion, arms_of(mapping, motion.skeleton.parents), moves, 0.995)


def test_a_hand_lifted_off_its_thigh_is_put_back_and_an_idle_arm_is_untouched(skinny) -> None:  # type: ignore[no-untyped-def]
    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    legs = CONTACT_PARTS.index("legs")
    assert _judged(ch, mapping, source, [0])[0, LEFT, legs] < 0.015  # the source touches
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    outward = torch.tensor([side * 0.05, 0.0, 0.0], dtype=torch.float64)  # away from the body
    target = _lifted(source, mapping, LEFT, outward)
    lifted = _judged(ch, mapping, target, list(range(10, 30, 4)))
    assert (lifted[:, LEFT, legs] > 0.025).all()  # lost, as the judge reads it
    out = hand_contacts.run(_context(ch, mapping, source, target), target)
    back = _judged(ch, mapping, out.motion, list(range(12, 28, 2)))
    assert (back[:, LEFT, legs] < 0.025).all()  # kept (the span's first frames are eased in by the smoothing)
    edge = _judged(ch, mapping, out.motion, [10])
    assert edge[0, LEFT, legs] < lifted[0, LEFT, legs] - 0.02
    assert out.report["preservation_after"] > out.report["preservation_before"]
    right = [mapping.joints[n] for n in ("RightArm", "RightForeArm", "RightHand")]
    assert torch.equal(out.motion.rotations[:, right], target.rotations[:, right])


def _hand_depth(ch: Character, mapping: JointMapping, motion: Motion, frames: list[int]) -> np.ndarray:
    """``(n,)`` the judge's deepest counted left-hand vertex (m) at ``frames``."""
    grot, gpos = motion.global_transforms()
    hand = reach_body(ch, mapping).body.hand_vertices["left"]
    with torch.no_grad():
        posed = ch.pose_vertices(grot[frames], gpos[frames]).double().numpy()
    return np.stack([measure_pose(ch, mapping, p).depth[hand].max() for p in posed])


def test_a_hand_pressed_into_its_thigh_is_moved_out_to_the_surface(skinny) -> None:  # type: ignore[no-untyped-def]
    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    legs = CONTACT_PARTS.index("legs")
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    inward = torch.tensor([-side * 0.03, 0.0, 0.0], dtype=torch.float64)  # into the thigh
    target = _lifted(source, mapping, LEFT, inward)
    pressed = _hand_depth(ch, mapping, target, list(range(10, 30, 4)))
    assert (pressed > 0.015).all()  # deeper than 1 cm as the judge reads it
    out = hand_contacts.run(_context(ch, mapping, source, target), target)
    assert out.report["frames_hand_in_body_before"] >= 20
    after = _hand_depth(ch, mapping, out.motion, list(range(12, 28, 2)))
    assert (after < 0.01).all()
    assert (_judged(ch, mapping, out.motion, list(range(12, 28, 4)))[:, LEFT, legs] < 0.025).all()  # still touching


SUNK_FRAMES = list(range(12, 28, 3))


def _sunk_a_few_millimetres(skinny) -> tuple[Motion, Motion]:  # type: ignore[no-untyped-def]
    """A hand resting 1.5 to 5 mm inside its thigh on :data:`SUNK_FRAMES` (a grip's hand in the other fist reads
    the same), and the stage's result."""
    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    target = _lifted(source, mapping, LEFT, torch.tensor([-side * 0.007, 0.0, 0.0], dtype=torch.float64))
    sunk = _hand_depth(ch, mapping, target, SUNK_FRAMES)
    assert (sunk > 0.0015).all() and (sunk < 0.005).all()  # shallower than a frame > 1 cm, but counted
    return target, hand_contacts.run(_context(ch, mapping, source, target), target).motion


def _hand_inside(ch: Character, mapping: JointMapping, motion: Motion, frames: list[int]) -> np.ndarray:
    """``(n,)`` how many left-hand vertices the judge counts inside a part (pen %v) at ``frames``."""
    grot, gpos = motion.global_transforms()
    hand = reach_body(ch, mapping).body.hand_vertices["left"]
    with torch.no_grad():
        posed = ch.pose_vertices(grot[frames], gpos[frames]).double().numpy()
    return np.stack([(measure_pose(ch, mapping, p).depth[hand] > 0).sum() for p in posed])


@pytest.mark.xfail(strict=True, reason="known gap: the stage moves a hand out only where it is deeper than 1 mm "
                   "(out_m), so a couple of a sunk hand's vertices stay inside, shallower than that, and pen %v counts "
                   "them at any depth")  # fmt: skip
def test_a_sunk_hand_keeps_at_most_a_fifth_of_its_vertices_inside(skinny) -> None:  # type: ignore[no-untyped-def]
    ch, mapping, _ = skinny
    target, out = _sunk_a_few_millimetres(skinny)
    inside = _hand_inside(ch, mapping, target, SUNK_FRAMES)
    assert (_hand_inside(ch, mapping, out, SUNK_FRAMES) <= 0.2 * inside).all()


def test_a_hand_sunk_a_few_millimetres_into_its_thigh_comes_out_too(skinny) -> None:  # type: ignore[no-untyped-def]
    """The judge's pen %v counts a vertex at any depth: a hand resting 1.5 to 5 mm inside its thigh is moved out
    to within the 1 mm line, still touching."""
    ch, mapping, _ = skinny
    target, out = _sunk_a_few_millimetres(skinny)
    sunk = _hand_depth(ch, mapping, target, SUNK_FRAMES)
    after = _hand_depth(ch, mapping, out, SUNK_FRAMES)
    assert (after < 0.5 * sunk).all() and (after < 0.0015).all(), (sunk, after)
    legs = CONTACT_PARTS.index("legs")
    assert (_judged(ch, mapping, out, SUNK_FRAMES)[:, LEFT, legs] < 0.025).all()  # still touching


def _pressed_for_four_frames(skinny, inward_m: float) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """The left hand pushed ``inward_m`` into its thigh for 4 frames, as a swinging hand brushes it on a walk: the
    judge's deepest hand vertex on frames 14-23 before and after the stage ``(10,)`` (m)."""
    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    inward = torch.tensor([-side * inward_m, 0.0, 0.0], dtype=torch.float64)  # into the thigh
    t = torch.arange(FRAMES, dtype=torch.float64)
    ease = torch.minimum(smoothstep((t - 14.0) / 3.0), smoothstep((23.0 - t) / 3.0))
    moves = torch.zeros(FRAMES, 2, 3, dtype=torch.float64)
    moves[:, LEFT] = ease[:, None] * inward
    target = apply_moves(source, arms_of(mapping, ch.skeleton.parents), moves, 0.995)
    frames = list(range(14, 24))
    out = hand_contacts.run(_context(ch, mapping, source, target), target)
    return _hand_depth(ch, mapping, target, frames), _hand_depth(ch, mapping, out.motion, frames)


def test_a_hand_pressed_into_its_thigh_for_a_few_frames_comes_out_too(skinny) -> None:  # type: ignore[no-untyped-def]
    before, after = _pressed_for_four_frames(skinny, 0.03)
    assert before.max() > 0.02
    assert after.max() < 0.006  # the smoothing does not average it away


def test_the_passes_take_a_deeper_brief_press_further_out(skinny) -> None:  # type: ignore[no-untyped-def]
    """Each pass's smoothed move takes a brief press only part of the way out: six passes leave 2.1 mm of a 2.6 cm
    press, three left 4.0 (docs/results.md, "Six passes of the hand contact stage")."""
    before, after = _pressed_for_four_frames(skinny, 0.035)
    assert before.max() > 0.022
    assert after.max() < 0.003


def test_a_move_out_of_a_part_keeps_the_contact_the_hand_rests_on() -> None:
    out = torch.zeros(1, 2, 3, dtype=torch.float64)
    out[0, LEFT] = torch.tensor([0.03, 0.02, 0.0])  # out of the thigh: 3 cm away from the belly, 2 cm along it
    toward = torch.zeros(1, 2, 4, 3, dtype=torch.float64)
    toward[0, LEFT, 1] = torch.tensor([-1.0, 0.0, 0.0])  # the belly (torso) lies at -x
    touch = torch.zeros(1, 2, 4, dtype=torch.bool)
    touch[0, LEFT, 1] = True
    slack = torch.full((1, 2, 4), 0.01, dtype=torch.float64)  # 1 cm more and the contact is lost
    kept = hand_contacts.kept_touching(out, toward, touch, slack)[0, LEFT]
    assert torch.allclose(kept, torch.tensor([0.01, 0.02, 0.0], dtype=torch.float64))
    touch[:] = False  # nothing touched: the move is left as it is
    assert torch.equal(hand_contacts.kept_touching(out, toward, touch, slack), out)


def test_a_hand_clear_in_the_source_is_moved_clear_of_the_torso(skinny) -> None:  # type: ignore[no-untyped-def]
    ch, mapping, rb = skinny
    source = _rest(ch)
    torso = CONTACT_PARTS.index("torso")
    assert _judged(ch, mapping, source, [0])[0, RIGHT, torso] > 0.05  # clear of the torso in the source
    target = _placed(ch, mapping, rb, source, RIGHT, "torso", 0.004)
    assert _judged(ch, mapping, target, [0])[0, RIGHT, torso] < 0.01  # a false contact as the judge reads it
    out = hand_contacts.run(_context(ch, mapping, source, target), target)
    after = _judged(ch, mapping, out.motion, list(range(0, FRAMES, 5)))
    assert (after[:, RIGHT, torso] >= 0.01).all()
    assert out.report["false_contacts_after"] < out.report["false_contacts_before"]


@pytest.mark.parametrize("clearance", [0.00002, -0.003])
def test_a_hand_grazing_or_in_a_part_the_source_keeps_clear_is_moved_clear_of_it(skinny, clearance: float) -> None:  # type: ignore[no-untyped-def]
    """A hand grazing the thigh (20 micrometres off it), or 3 mm into it, where the source holds it far from the
    legs: the hand ends clear of them, as the judge reads it, on every frame."""
    ch, mapping, rb = skinny
    source = _rest(ch)
    legs = CONTACT_PARTS.index("legs")
    assert _judged(ch, mapping, source, [0])[0, LEFT, legs] > 0.05  # clear of the legs in the source
    target = _placed(ch, mapping, rb, source, LEFT, "left_leg", clearance)
    assert _judged(ch, mapping, target, [0])[0, LEFT, legs] < 0.001  # a false contact as the judge reads it
    out = hand_contacts.run(_context(ch, mapping, source, target), target)
    after = _judged(ch, mapping, out.motion, list(range(0, FRAMES, 5)))
    assert (after[:, LEFT, legs] >= 0.01).all(), after[:, LEFT, legs]


def test_a_hand_on_or_in_a_part_it_should_clear_is_moved_out_along_the_way_from_the_bones() -> None:
    """The wanted move off a part the source keeps clear follows the way out from the part's bones, by what is
    missing to ``clear_m``: also where the hand's nearest surface point gives no direction (the hand on the surface,
    or in the part, distance 0: the stage used to leave such a hand where it was, or push it one way, then back)."""
    p = hand_contacts.HandContactParams()
    src = torch.full((1, 2, 4), float("inf"), dtype=torch.float64)  # the source far from every part
    nan = torch.full((1, 2, 4, 3), float("nan"), dtype=torch.float64)
    distance = torch.full((1, 2, 4), float("inf"), dtype=torch.float64)
    legs = CONTACT_PARTS.index("legs")
    distance[0, LEFT, legs] = 0.0
    hand_point, surface_point = nan.clone(), nan.clone()
    hand_point[0, LEFT, legs] = surface_point[0, LEFT, legs] = torch.tensor([0.2, 0.5, 0.0], dtype=torch.float64)
    state = hand_contacts.HandState(distance, hand_point, surface_point)
    away = torch.zeros(1, 2, 4, 3, dtype=torch.float64)
    away[0, LEFT, legs] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    move, weight = hand_contacts.wanted_moves(src, state, HandDepth.empty(1), 1.0, p, away)
    assert torch.allclose(move[0, LEFT], torch.tensor([p.clear_m, 0.0, 0.0], dtype=torch.float64))
    assert float(weight[0, LEFT]) == 1.0 and torch.equal(move[0, RIGHT], torch.zeros(3, dtype=torch.float64))


def test_the_way_out_of_a_part_runs_from_its_nearest_bone() -> None:
    gpos = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]], dtype=torch.float64)  # two bones, an L
    bones = torch.tensor([[0, 1], [1, 2], [2, 2]])
    points = torch.tensor([[[0.1, 0.5, 0.0], [0.5, 1.2, 0.0], [1.5, 1.0, 0.0], [0.0, 0.5, 0.0]]], dtype=torch.float64)
    way = away_from_bones(points, gpos, bones)[0]
    assert torch.allclose(way[:3], torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64))
    assert torch.equal(way[3], torch.zeros(3, dtype=torch.float64))  # on a bone: no way out read


def test_the_moves_smoothing_follows_defined_frames_and_never_overshoots() -> None:
    wanted = torch.zeros(90, 1, dtype=torch.float64)
    wanted[30:60] = 1.0
    weight = torch.full((90,), 0.1, dtype=torch.float64)
    weight[30:60] = 1.0
    fit = weighted_smooth(wanted, weight, 3.0)[:, 0]
    assert float((fit[36:54] - 1.0).abs().max()) < 0.02  # follows inside the span
    assert float(fit[:15].abs().max()) < 0.01 and float(fit[75:].abs().max()) < 0.01  # nothing far from it
    assert float(fit.min()) >= 0.0 and float(fit.max()) <= 1.0  # a weighted mean: no ringing
    jerk = (fit[3:] - 3 * fit[2:-1] + 3 * fit[1:-2] - fit[:-3]).abs().max()
    assert float(jerk) < 0.1  # the wanted curve's own third difference at its steps: 1


def test_a_body_without_a_mapped_forearm_is_left_as_it_is() -> None:
    from tests.core.test_collisions import _arm_boxes, _pushed_in
    from tests.core.test_collisions import _context as boxes_context

    ch = _arm_boxes()  # Hips, Spine, LeftArm, LeftHand: no forearm to bend
    motion = _pushed_in(ch, 0.02, frames=4)
    out = hand_contacts.run(boxes_context(ch, motion), motion)
    assert out.motion is motion and out.report["frames_changed"] == 0


def test_part_trees_posed_in_smaller_chunks_give_the_same_stage(skinny, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A body whose part trees and posed rows would not fit the chunk budget is posed a few frames at a time (a
    95k-vertex body held 342 MB per 64 frames): the hand contact stage gives the same motion as in whole chunks."""
    import retarget_core.contacts.hand_reach as hr

    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    target = _lifted(source, mapping, LEFT, torch.tensor([-side * 0.03, 0.0, 0.0], dtype=torch.float64))
    whole = hand_contacts.run(_context(ch, mapping, source, target), target)
    assert rb.chunk_frames(64) == 64
    frame_bytes = 48 * sum((2 << t.depth) - 1 for t in rb.trees.values())  # every part's boxes of one frame
    frame_bytes += 24 * (int(rb.read_vertices()[-1]) + 1)  # and its posed rows
    monkeypatch.setattr(hr, "CHUNK_BUDGET_BYTES", 7 * frame_bytes)
    assert rb.chunk_frames(64) == 7
    small = hand_contacts.run(_context(ch, mapping, source, target), target)
    assert whole.report["frames_changed"] > 0
    assert torch.allclose(small.motion.rotations, whole.motion.rotations, atol=1e-9, rtol=0)


def test_measuring_both_on_one_posing_equals_measuring_each(skinny) -> None:  # type: ignore[no-untyped-def]
    """The stage poses each chunk once for its distances and its depths (``measure_both``): the same figures as
    :func:`measure_hands` and as the depths of all the frames posed at once, on every frame and on a subset."""
    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    target = _lifted(source, mapping, LEFT, torch.tensor([-side * 0.03, 0.0, 0.0], dtype=torch.float64))
    ctx = _context(ch, mapping, source, target)
    p = hand_contacts.HandContactParams()
    src = hand_contacts.source_groups(ctx)
    every = torch.arange(target.num_frames)
    state, depth = hand_contacts.measure_both(ctx, rb, target, src, p, every, chunk=7)
    some = every[::3]
    again, deeper = hand_contacts.measure_both(ctx, rb, target, src, p, some, state, depth, chunk=5)
    for frames, got, (s, d) in ((every, (state, depth), (None, None)), (some, (again, deeper), (state, depth))):
        hands = hand_contacts.measure_hands(ctx, rb, target, src, p, frames, s)
        inside = HandDepth.empty(target.num_frames) if d is None else HandDepth(*(t.clone() for t in vars(d).values()))
        whole = hand_depths(PosedParts(rb, posed_for_reach(rb, ch, target, frames)), p.depth_cap_m * rb.scale)
        inside.depth[frames], inside.hand_point[frames], inside.surface_point[frames] = vars(whole).values()
        for a, b in ((got[0], hands), (got[1], inside)):
            for x, y in zip(vars(a).values(), vars(b).values(), strict=True):
                assert torch.equal(x.nan_to_num(-1.0), y.nan_to_num(-1.0))
    assert bool((depth.depth > 0).any()) and bool(torch.isfinite(state.distance).any())


def test_a_put_back_contact_may_cost_a_few_millimetres_of_arm_depth(skinny, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A short-armed character's hand put back on its thigh brings the forearm into the body: the never-worse
    check keeps a move that regains a source contact while the arms' deepest point stays within
    ``trade_depth_m`` (here every moved frame reads 3 mm deeper and much more volume) and withdraws it beyond."""
    import retarget_core.refine.judged_check as jc

    ch, mapping, rb = skinny
    source = _placed(ch, mapping, rb, _hanging(ch, mapping, rb), LEFT, "left_leg", 0.004)
    side = float(torch.sign(source.global_transforms()[1][0, mapping.joints["LeftHand"], 0]))
    target = _lifted(source, mapping, LEFT, torch.tensor([side * 0.05, 0.0, 0.0], dtype=torch.float64))
    fore = mapping.joints["LeftForeArm"]
    real_check = jc.arm_check

    def deeper_when_moved(ctx, rb_, motion, frames, chunk=64):  # type: ignore[no-untyped-def]
        check = real_check(ctx, rb_, motion, frames, chunk)
        moved = (motion.rotations[frames, fore] - target.rotations[frames, fore]).abs().amax(dim=-1) > 1e-6
        check.max_depth[moved] += 0.003 * rb_.scale
        check.volume[moved] += 1e-4
        return check

    monkeypatch.setattr(jc, "arm_check", deeper_when_moved)
    legs = CONTACT_PARTS.index("legs")
    ctx = _context(ch, mapping, source, target)
    middle = list(range(16, 25, 4))  # the frames eased in and out gain nothing: their withdrawal ramps 4 frames in
    traded = hand_contacts.run(ctx, target)
    assert (_judged(ch, mapping, traded.motion, middle)[:, LEFT, legs] < 0.025).all()
    strict = hand_contacts.run(ctx, target, hand_contacts.HandContactParams(trade_depth_m=0.002))
    assert (_judged(ch, mapping, strict.motion, middle)[:, LEFT, legs] > 0.025).all()
    assert strict.report["withdrawn_frames"] > traded.report["withdrawn_frames"]


def test_interlocked_fists_are_moved_apart_and_a_hand_in_the_other_arm_alone_as_before() -> None:
    """Both hands deeper than the bound in each other's arm (a grip): each one's way out of the other arm points
    away from the other wrist, as long as its depth; one hand in the other arm alone keeps its nearest exit."""
    inside = HandDepth.empty(2)
    other = 2
    inside.depth[:, :, other] = torch.tensor([[0.02, 0.01], [0.02, 0.0]], dtype=torch.float64)
    inside.hand_point[:, :, other] = 0.0
    inside.surface_point[:, :, other] = torch.tensor([0.0, -0.02, 0.0], dtype=torch.float64)  # both exits: down
    wrists = torch.tensor([[[0.0, 0.0, 0.1], [0.0, 0.0, 0.0]]] * 2, dtype=torch.float64)  # left 10 cm along +z
    apart = hand_contacts.grip_apart(inside, wrists, 0.005)
    ways = apart.surface_point - apart.hand_point
    assert torch.allclose(ways[0, 0, other], torch.tensor([0.0, 0.0, 0.02], dtype=torch.float64))
    assert torch.allclose(ways[0, 1, other], torch.tensor([0.0, 0.0, -0.01], dtype=torch.float64))
    assert torch.equal(ways[1, :, other], (inside.surface_point - inside.hand_point)[1, :, other])  # not a grip
    assert hand_contacts.grip_apart(inside, None, 0.005) is inside  # one arm mapped: nothing to pair
