"""The never-worse check both collision stages share (:mod:`retarget_core.refine.never_worse`), on a toy stage
whose penetration grows with its change on some frames: worse frames fall back toward the input, the others keep
the change, a repair is tried before any fallback, and what was never measured goes back to the input."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.metrics.depth import VertexDepths
from retarget_core.refine.collision_check import ContactInstances, FrameCheck
from retarget_core.refine.never_worse import FallbackSettings, NeverWorse, run_never_worse
from retarget_core.refine.temporal import fallback_weights

F = 40
NO_CONTACTS = ContactInstances(torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long))
SETTINGS = FallbackSettings(rounds=4, factor=0.5, floor=0.2, ramp=4)


@dataclass(frozen=True)
class Limits:
    worse_volume_fraction: float = 0.02
    worse_volume_m3: float = 1e-9
    worse_depth_m: float = 0.002
    contact_ok_m: float = 0.02


def _check(frames: Tensor, depth: Tensor) -> FrameCheck:
    n = len(frames)
    return FrameCheck(frames, depth * 1e-4, depth, (depth > 0).float(), VertexDepths.from_dense(torch.zeros(n, 1)),
                      torch.zeros(0))  # fmt: skip


def _toy(harm: Tensor):
    """A stage whose change deepens frame f by ``harm[f] * weight[f]`` (m) over an input 1 cm deep."""
    before = _check(torch.arange(F), torch.full((F,), 0.01))

    def measure(weight: Tensor, frames: Tensor) -> FrameCheck:
        return _check(frames, 0.01 + harm[frames] * weight[frames])

    return before, measure


def test_worse_frames_fall_back_and_the_others_keep_the_change() -> None:
    harm = torch.zeros(F)
    harm[20] = 0.05  # 5 cm deeper with the whole change: worse at any weight above 0.04
    before, measure = _toy(harm - 0.005)  # every other frame 5 mm shallower: better
    guard = run_never_worse(NeverWorse.start(before, NO_CONTACTS), torch.arange(F), measure, Limits(), 1.0, SETTINGS)
    assert float(guard.weight[20]) == 0.0  # halved to 0.5, 0.25, then dropped below the floor
    assert float(guard.weight[0]) == 1.0 and float(guard.weight[-1]) == 1.0  # far from it the change stays whole
    assert 0.0 < float(guard.weight[18]) < 1.0  # ramped around it
    assert bool((guard.final.max_depth <= before.max_depth + 0.002).all())  # never worse on any frame


def test_a_repair_is_tried_before_falling_back() -> None:
    harm = torch.zeros(F)
    harm[10] = 0.05
    before, measure = _toy(harm)
    calls: list[list[int]] = []

    def repair(after: FrameCheck, worse: Tensor) -> Tensor | None:
        calls.append(after.frames[worse].tolist())
        harm[10] = 0.0  # the repair mends it
        return after.frames[worse]

    guard = run_never_worse(NeverWorse.start(before, NO_CONTACTS), torch.arange(F), measure, Limits(), 1.0,
                            SETTINGS, repair, repair_rounds=2)  # fmt: skip
    assert calls == [[10]]
    assert bool((guard.weight == 1.0).all())  # nothing fell back


def test_changes_never_measured_go_back_to_the_input() -> None:
    harm = torch.full((F,), 0.05)  # worse everywhere, at every weight: rounds run out
    before, measure = _toy(harm)
    one_round = FallbackSettings(rounds=1, factor=0.5, floor=0.2, ramp=4)
    guard = run_never_worse(NeverWorse.start(before, NO_CONTACTS), torch.arange(F), measure, Limits(), 1.0, one_round)
    assert bool((guard.weight == 0.0).all())
    assert torch.equal(guard.final.max_depth, before.max_depth)


def test_a_change_worse_at_every_weight_goes_back_with_a_blend_not_a_step() -> None:
    harm = torch.zeros(F)
    harm[15:25] = 0.05  # worse at any weight: falls back on every round, then settles
    before, measure = _toy(harm - 0.005)
    ramp8 = FallbackSettings(rounds=2, factor=0.5, floor=0.2, ramp=8)
    guard = run_never_worse(NeverWorse.start(before, NO_CONTACTS), torch.arange(F), measure, Limits(), 1.0, ramp8)
    assert bool((guard.weight[15:25] == 0.0).all())
    assert float(guard.weight.diff().abs().max()) < 0.25  # a smoothstep over 8 frames, never a jump to 0
    assert guard.settle_rounds >= 1  # the rounds ran out: what was left settled with a blend
    assert bool((guard.final.max_depth <= before.max_depth + 0.002).all())


def test_blends_between_two_close_spans_do_not_leave_blips() -> None:
    cap = torch.ones(F)
    cap[10], cap[14] = 0.0, 0.0  # two withdrawn frames 4 apart: the frames between go back too
    w = fallback_weights(cap, 8)
    assert bool((w[10:15] == 0.0).all())
    assert bool((w <= cap).all())
    assert float(w[0]) == 1.0 and float(w[-1]) == 1.0
    far = torch.ones(F)
    far[5], far[30] = 0.0, 0.0  # 25 apart: two blends, full weight between
    assert float(fallback_weights(far, 8)[17]) == 1.0


def test_a_frame_the_stage_flags_falls_back_like_a_deeper_one() -> None:
    """A stage may read a frame as worse by its own measure (FrameCheck.flagged): same depths everywhere, frame 10
    flagged while any of the change stays there."""
    before, _ = _toy(torch.zeros(F))

    def measure(weight: Tensor, frames: Tensor) -> FrameCheck:
        check = _check(frames, torch.full((len(frames),), 0.01))
        return FrameCheck(check.frames, check.volume, check.max_depth, check.count, check.depth, check.contact,
                          flagged=(frames == 10) & (weight[frames] > 0))  # fmt: skip

    guard = run_never_worse(NeverWorse.start(before, NO_CONTACTS), torch.arange(F), measure, Limits(), 1.0, SETTINGS)
    assert float(guard.weight[10]) == 0.0
    assert float(guard.weight[0]) == 1.0 and float(guard.weight[-1]) == 1.0


def test_the_arm_stages_check_withdraws_over_the_ramp_it_is_given(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """:func:`judged_check.never_worse_weights` with a toy arm check (frame 20 worse with any of the change): the
    change is withdrawn around it over ``ramp`` frames, so a shorter ramp keeps it whole nearer to the worse frame."""
    from types import SimpleNamespace

    from retarget_core.refine import judged_check

    harm = torch.zeros(F)
    harm[20] = 0.05

    def fake_arm_check(ctx, rb, out, frames):  # type: ignore[no-untyped-def]
        return _check(frames, 0.01 + harm[frames] * out.weight[frames])

    monkeypatch.setattr(judged_check, "arm_check", fake_arm_check)
    ctx = SimpleNamespace(target=SimpleNamespace(num_vertices=1))
    rb = SimpleNamespace(scale=1.0)
    motion = SimpleNamespace(num_frames=F, fps=30.0, weight=torch.zeros(F))  # the input: none of the change

    def weights(ramp: int) -> Tensor:
        return judged_check.never_worse_weights(ctx, rb, motion, lambda w: SimpleNamespace(weight=w),  # type: ignore[arg-type]
                                                torch.arange(F), ramp=ramp)  # fmt: skip

    short, default = weights(2), weights(8)  # 8: the collision stage's ramp
    assert float(short[20]) == 0.0 and float(default[20]) == 0.0
    assert bool((short[:17] == 1.0).all()) and bool((short[24:] == 1.0).all())
    assert float(default[16]) < 1.0 and float(default[24]) < 1.0
    assert bool((short >= default).all())


def test_an_excused_frame_keeps_its_deeper_change_and_a_flagged_one_falls_back() -> None:
    harm = torch.zeros(F)
    harm[[10, 30]] = 0.005  # 5 mm deeper with the whole change on two frames
    before, measure_toy = _toy(harm)

    def measure(weight: Tensor, frames: Tensor) -> FrameCheck:
        check = measure_toy(weight, frames)
        check.excused = frames == 10  # the stage accepts frame 10's depth for what it gained there
        check.flagged = (frames == 10) & (weight[frames] > 0.3)  # ... but a flag still counts
        return check

    guard = run_never_worse(NeverWorse.start(before, NO_CONTACTS), torch.arange(F), measure, Limits(), 1.0, SETTINGS)
    assert float(guard.weight[30]) == 0.0  # deeper and not excused: withdrawn
    assert float(guard.weight[10]) == 0.25  # excused depth, flagged until halved twice
