"""Foot lock: every plant of the source held at one place on the floor, by analytic two-bone leg IK.

Runs last among the refinement stages (METHOD-NOTES: foot locks fight the collision stage otherwise), then
re-checks the legs' collisions and reports them (it does not re-resolve them).

1. Plants: per foot, the contiguous spans where the source has that foot planted as the judge defines it
   (``ctx.planted``: toe at most 3 cm above its rest height, toe and ankle moved at most 1 cm per 1/30 s,
   5-frame majority), so what is locked is what the judged foot accuracy compares. Without those labels,
   where the source has toe and heel planted (``ctx.feet``; a rig without toes uses the heel alone).
2. Lock: each plant gets one foot pose for all its frames (SAN's choice, METHOD-NOTES): the ankle's mean
   horizontal position over the span; the foot's mean orientation, made flat (its rest orientation turned
   about the vertical) when it tilts little; the toe's mean bend, also flattened; the height that puts the
   lowest foot vertex on the floor.
3. Blend: around each plant the correction fades in and out over a few frames with a smoothstep, as an
   *offset* added to the copy's own foot motion (not a blend toward a fixed point): a foot that lifts off
   keeps its own speed, so the frames the source calls "moving" still move (foot accuracy).
4. IK: hip-knee-ankle analytic two-bone IK (:mod:`retarget_core.refine.two_bone_ik`) with the knee's own
   forward axis as pole, reach clamped short of full extension (or at the leg's own, where the input holds it
   straighter: bent to the clamp on a few frames, a knee jerks); where a leg cannot reach its lock the pelvis
   is lowered, smoothly (a dilated, windowed drop that is never less than what each frame needs); frames that
   only the pelvis drop touches keep their feet where the copy had them.
5. Floor: heights come from a rigid model of the foot's vertices (each on its dominant joint, Foot or
   ToeBase); against skinning it is off by at most 1 mm on the shared bodies (measured), inside the 1 mm the
   locks float. A foot outside its plants (fades, pelvis drop, and a free foot the copy dips under the floor,
   such as a dancer's foot sliding along it) that would be below the floor is raised, smoothly (the toe kept
   above it): by the whole body where no foot is planted (the root rises with least jerk: no foot moves against
   the hips, which the judged end-effector error reads), by the leg for what the body cannot give (beside a
   planted foot, and fading in from each plant).
6. Free feet stay free: outside its plants a foot's toe joint is raised, the same way, to at least the height
   the source's toe stands above its own rest height (``ctx.toe_heights``, at 1.80 m, scaled to the body), up to
   5 mm over the judge's 3 cm plant line. A foot the source holds a few centimetres off the floor (a hovering,
   still foot) is not planted for the judge; the copy on other proportions, and the stages before, carried it
   lower, under that line, where it read as planted (docs/results.md, "Free feet at the source's height").

The stage computes on the CPU (a 300-frame clip is a few hundred small batched operations: faster there than
on a GPU) and returns the motion on the device it came on.

Lengths are given at a 1.80 m character and scaled to the body; durations in seconds and converted to frames
at the clip's rate.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.body_parts import CLUSTERS
from retarget_core.character import Character
from retarget_core.context import RefineContext, StageOutcome, computes_on_cpu
from retarget_core.energy.sdf import effective_depth, sample_pairs, segment_matrices
from retarget_core.metrics.feet_acceptance import foot_vertices_of
from retarget_core.motion import Motion
from retarget_core.refine.floor import FloorParams, least_jerk_lift
from retarget_core.refine.temporal import smoothstep
from retarget_core.refine.two_bone_ik import two_bone_ik
from retarget_core.skeleton import subtree

REFERENCE_HEIGHT_M = 1.80
REFERENCE_FPS = 30.0
SIDES: tuple[str, ...] = ("Left", "Right")
REST_FORWARD = (0.0, 0.0, 1.0)  # normalised rest poses face +Z: the knee's forward axis at rest


@dataclass(frozen=True)
class FootLockParams:
    """Settings (lengths at a 1.80 m character)."""

    # Fade in/out of each lock: SAN blends +-5 frames at 30 fps, orangeduck inertialises over 0.1 s.
    blend_seconds: float = 0.15
    # Largest hip-to-ankle distance as a share of the leg's length: short of a locked knee (about an
    # 11-degree bend at the knee), where the analytic solution's knee angle is ill-conditioned; a leg the input
    # holds straighter keeps its own extension (two_bone_ik).
    max_reach: float = 0.995
    # Lowest foot vertex of a locked foot above the floor: 1 mm keeps rounding from counting as ground
    # penetration; the judged float window is -5..+10 mm.
    lock_float_m: float = 0.001
    # A plant's mean foot orientation tilting less than the first angle (degrees) is made fully flat, more
    # than the second kept as it is, in between blended: a foot standing flat is shown flat on the floor, a
    # foot on tiptoe stays on tiptoe.
    flat_tilt_deg: tuple[float, float] = (15.0, 30.0)
    # Pelvis drop: spread (dilated and windowed) over this many seconds each side, and never more than this.
    pelvis_smooth_seconds: float = 0.2
    max_pelvis_drop_m: float = 0.15
    # Where each plant is held horizontally: "mean" (SAN: the span's mean, half the copy's drift at either
    # end) or "onset" (orangeduck: where the foot lands, so the fade-in adds no horizontal motion).
    lock_at: str = "mean"
    # Re-check leg collisions (leg vs other leg and arms) before and after the stage, on the changed frames.
    check_collisions: bool = True
    # Penetration counted in the collision check beyond this depth (the metrics' tolerance).
    penetration_tolerance_m: float = 0.003
    # A free foot's toe is kept as high above its rest height as the source's, up to this: 5 mm over the judge's
    # 3 cm plant line, the least lift that keeps a free foot free (a full lift costs end-effector error).
    free_toe_height_m: float = 0.035
    # The whole body's share of a free foot's depth under the floor fades in over this from each plant (held at 0
    # there): shorter, the least-jerk lift overshoots the dip (0.2 s: 5.4 cm for a 4 cm dip, 0.3 s: 4.5; built case).
    body_lift_fade_seconds: float = 0.3


@dataclass
class Leg:
    """The joints of one leg on the target skeleton (toe -1 when absent) and its label columns."""

    side: str
    hip: int
    knee: int
    ankle: int
    toe: int
    toe_column: int
    heel_column: int


@dataclass
class Plant:
    """One plant: frames ``start..stop`` inclusive and its ramps (frames faded before and after)."""

    start: int
    stop: int
    ramp_in: int
    ramp_out: int


def legs_of(ctx: RefineContext) -> list[Leg]:
    """Both legs of the target (columns of ``ctx.feet``: left toe, left heel, right toe, right heel)."""
    m = ctx.target_mapping.joints
    sk = ctx.target.skeleton
    out = []
    for k, side in enumerate(SIDES):
        ankle = m[f"{side}Foot"]
        toe = m.get(f"{side}ToeBase", -1)
        if toe >= 0 and sk.parents[toe] != ankle:
            toe = -1  # the toe lock needs the toe directly under the ankle
        out.append(Leg(side, m[f"{side}UpLeg"], m[f"{side}Leg"], ankle, toe, 2 * k, 2 * k + 1))
    return out


def planted_columns(labels: Tensor, available: Tensor, leg: Leg) -> Tensor:
    """``(F,)`` bool: the source has this foot planted (toe and heel; the heel alone without a toe column)."""
    heel = labels[:, leg.heel_column] if bool(available[leg.heel_column]) else torch.zeros_like(labels[:, 0])
    if bool(available[leg.toe_column]):
        return heel & labels[:, leg.toe_column]
    return heel


def source_plants(ctx: RefineContext, legs: list[Leg], frames: int) -> list[Tensor]:
    """Per leg, ``(F,)`` bool: the source has that foot planted. The judge's labels (``ctx.planted``: toe low,
    toe and ankle still, majority-smoothed) where the pipeline gives them, so that what is locked is what the
    judged foot accuracy compares; otherwise toe and heel of ``ctx.feet``."""
    if ctx.planted is not None:
        return [ctx.planted[:frames, k].bool().cpu() for k in range(len(legs))]
    labels = ctx.feet.labels[:frames]
    return [planted_columns(labels, ctx.feet.available, leg) for leg in legs]


def plant_spans(planted: Tensor) -> list[tuple[int, int]]:
    """Contiguous runs ``[(start, stop)]`` (inclusive) of ``planted (F,)``."""
    p = planted.to(torch.int8)
    edges = torch.diff(torch.cat([p.new_zeros(1), p, p.new_zeros(1)]))
    starts = torch.nonzero(edges == 1).flatten().tolist()
    stops = (torch.nonzero(edges == -1).flatten() - 1).tolist()
    return list(zip(starts, stops, strict=True))


def make_plants(spans: list[tuple[int, int]], frames: int, blend: int) -> list[Plant]:
    """Plants with ramps of ``blend`` frames, shortened so neighbouring plants' ramps never overlap."""
    out = []
    for k, (a, b) in enumerate(spans):
        gap_before = a - (spans[k - 1][1] + 1) if k > 0 else a
        gap_after = (spans[k + 1][0] - 1 - b) if k + 1 < len(spans) else frames - 1 - b
        ramp_in = min(blend, gap_before if k == 0 else gap_before // 2)
        ramp_out = min(blend, gap_after if k + 1 == len(spans) else gap_after // 2)
        out.append(Plant(a, b, max(0, ramp_in), max(0, ramp_out)))
    return out


def _segment_mean_rotation(q: Tensor, seg: Tensor, count: int) -> Tensor:
    """Per segment, the sign-aligned normalised mean ``(P, 4)`` of quaternions ``q (M, 4)`` labelled ``seg``."""
    first = torch.zeros(count, 4, dtype=q.dtype).index_copy_(0, seg.flip(0), q.flip(0))  # first of each
    sign = torch.sign((q * first[seg]).sum(-1, keepdim=True))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    return rot.normalize(torch.zeros(count, 4, dtype=q.dtype).index_add_(0, seg, q * sign))


def _heading(delta: Tensor) -> tuple[Tensor, Tensor]:
    """For world rotations ``delta (..., 4)`` from the rest pose: the rotation about +Y with the same heading,
    and the tilt (degrees) of the rotated up axis from vertical."""
    fwd = rot.apply(delta, torch.tensor(REST_FORWARD, dtype=delta.dtype).expand(*delta.shape[:-1], 3))
    up = rot.apply(delta, torch.tensor([0.0, 1.0, 0.0], dtype=delta.dtype).expand(*delta.shape[:-1], 3))
    h = 0.5 * torch.atan2(fwd[..., 0], fwd[..., 2])
    z = torch.zeros_like(h)
    tilt = torch.rad2deg(torch.acos(up[..., 1].clamp(-1.0, 1.0)))
    return torch.stack([z, torch.sin(h), z, torch.cos(h)], -1), tilt


def _slerp(a: Tensor, b: Tensor, t: Tensor) -> Tensor:
    a, b = torch.broadcast_tensors(a, b)
    return rot.slerp(a, b, t.expand(a.shape[:-1]))


@dataclass
class FootModel:
    """Rigid stand-in for a foot's vertices: each vertex ``(N, 3)`` in its dominant joint's rest frame, and
    whether that joint is the toe ``(N,)``."""

    local: Tensor
    on_toe: Tensor


def foot_model(
    character: Character, ctx: RefineContext, leg: Leg, vertex_index: Tensor, rest_rot: Tensor, rest_pos: Tensor
) -> FootModel:
    seg_names = [ctx.parts.names[int(s)] for s in ctx.parts.vertex_part[vertex_index]]
    on_toe = torch.tensor([n.endswith("ToeBase") and leg.toe >= 0 for n in seg_names], dtype=torch.bool)
    v = character.vertices[vertex_index]
    local = torch.empty_like(v)
    for mask, j in ((~on_toe, leg.ankle), (on_toe, leg.toe)):
        if bool(mask.any()):
            local[mask] = rot.apply(rot.inv(rest_rot[j]), v[mask] - rest_pos[j])
    return FootModel(local, on_toe)


@dataclass
class LegPlan:
    """Per-frame goals of one leg: ankle target ``(F, 3)``, foot world rotation ``(F, 4)``, toe local rotation
    ``(F, 4)`` (or None), whether the leg is driven ``(F,)`` and whether the frame is inside a plant ``(F,)``."""

    target: Tensor
    foot_rotation: Tensor
    toe_local: Tensor | None
    driven: Tensor
    inside: Tensor


@dataclass
class Locks:
    """The locked pose of every frame inside one leg's plants: frames ``(M,)``, plant of each ``(M,)``, the
    pivot ``(P, 3)`` per plant (toe joint, or ankle without toes), the ankle target ``(M, 3)``, the foot world
    rotation ``(M, 4)`` and the toe local rotation ``(M, 4)`` (None without toes)."""

    frames: Tensor
    plant: Tensor
    pivot: Tensor
    ankle: Tensor
    foot_rotation: Tensor
    toe_local: Tensor | None


def _up_row(q: Tensor) -> Tensor:
    """Second row ``(M, 3)`` of the rotation matrices of ``q (M, 4)``: ``y`` of a rotated vector is its dot
    product with this row."""
    x, y, z, w = q.unbind(-1)
    return torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)


def _lowest_foot(model: FootModel, foot_rot: Tensor, toe_world: Tensor | None, toe_offset: Tensor | None) -> Tensor:
    """``(M,)`` lowest foot-vertex height relative to the pivot (toe joint; the ankle without toes) for foot
    world rotations ``(M, 4)`` and toe world rotations ``(M, 4)``; ``toe_offset (3,)``: toe in the foot frame."""
    local = model.local[~model.on_toe]
    if toe_offset is not None:
        local = local - toe_offset
    low = (_up_row(foot_rot) @ local.T).amin(-1)
    if toe_world is not None and bool(model.on_toe.any()):
        low = torch.minimum(low, (_up_row(toe_world) @ model.local[model.on_toe].T).amin(-1))
    return low


def lock_leg(
    leg: Leg, plants: list[Plant], model: FootModel, grot: Tensor, gpos: Tensor, sk_rest: tuple[Tensor, Tensor, Tensor],
    params: FootLockParams, scale: float,
) -> Locks:  # fmt: skip
    """The locks of one leg's plants (module doc, step 2), vectorised over every planted frame.

    With a toe joint, the toe is the pivot: held at one place, flat, its sole on the floor; the foot above it
    keeps the copy's own roll (a heel rising at the end of the stance rises), its plant's mean tilt and
    heading removed, and never rolls the heel under the floor. Without a toe, the ankle is held, flat.
    Each plant's lowest foot vertex is put on the floor by the rigid foot model."""
    rest_rot, rest_pos, toe_offset_all = sk_rest
    frames = torch.cat([torch.arange(p.start, p.stop + 1) for p in plants])
    plant = torch.cat([torch.full((p.stop - p.start + 1,), k, dtype=torch.long) for k, p in enumerate(plants)])
    count = len(plants)
    n_per = torch.bincount(plant, minlength=count).to(gpos.dtype)
    q = grot[frames, leg.ankle]
    mean_q = _segment_mean_rotation(q, plant, count)
    yaw, tilt = _heading(rot.mul(mean_q, rot.inv(rest_rot[leg.ankle])))
    lo, hi = params.flat_tilt_deg
    keep = ((tilt - lo) / max(hi - lo, 1e-6)).clamp(0.0, 1.0)  # (P,) 0: made flat, 1: kept
    flat_foot = rot.mul(yaw, rest_rot[leg.ankle].expand(count, 4))
    correction = _slerp(rot.mul(flat_foot, rot.inv(mean_q)), rot.identity(count, dtype=q.dtype), keep)  # (P, 4)
    pivot_joint = leg.toe if leg.toe >= 0 else leg.ankle
    pivot = torch.zeros(count, 3, dtype=gpos.dtype).index_add_(0, plant, gpos[frames, pivot_joint]) / n_per[:, None]
    if params.lock_at == "onset":
        pivot[:, [0, 2]] = gpos[torch.tensor([p.start for p in plants]), pivot_joint][:, [0, 2]]
    float_m = params.lock_float_m * scale
    if leg.toe < 0:
        foot_rot = _slerp(flat_foot, mean_q, keep)[plant]
        low = _lowest_foot(model, _slerp(flat_foot, mean_q, keep), None, None)
        pivot[:, 1] = float_m - low
        return Locks(frames, plant, pivot, pivot[plant], rot.normalize(foot_rot), None)
    toe_offset = toe_offset_all[leg.toe]
    mean_toe = _segment_mean_rotation(grot[frames, leg.toe], plant, count)
    flat_toe = rot.mul(yaw, rest_rot[leg.toe].expand(count, 4))
    toe_world = _slerp(flat_toe, mean_toe, keep)  # (P, 4)
    foot_rot = rot.normalize(rot.mul(correction[plant], q))
    # Never roll the heel under the floor: bisect toward the plant's flat (or kept) foot where it would.
    base = _slerp(flat_foot, mean_q, keep)[plant]
    floor_low = _lowest_foot(model, base, None, toe_offset)  # the base foot's lowest point below the pivot
    low = _lowest_foot(model, foot_rot, None, toe_offset)
    bad = low < floor_low - 0.001 * scale
    if bool(bad.any()):
        lo_s, hi_s = torch.zeros(int(bad.sum())), torch.ones(int(bad.sum()))
        a, b, f_low = base[bad], foot_rot[bad], floor_low[bad]
        for _ in range(8):
            mid = 0.5 * (lo_s + hi_s)
            ok = _lowest_foot(model, _slerp(a, b, mid), None, toe_offset) >= f_low - 0.001 * scale
            lo_s, hi_s = torch.where(ok, mid, lo_s), torch.where(ok, hi_s, mid)
        foot_rot[bad] = _slerp(a, b, lo_s)
    low_all = _lowest_foot(model, base, toe_world[plant], toe_offset)
    pivot[:, 1] = float_m - torch.zeros(count, dtype=gpos.dtype).index_add_(0, plant, low_all) / n_per
    ankle = pivot[plant] - rot.apply(foot_rot, toe_offset.expand(len(frames), 3))
    toe_local = rot.normalize(rot.mul(rot.inv(foot_rot), toe_world[plant]))
    return Locks(frames, plant, pivot, ankle, foot_rot, toe_local)


def plan_leg(leg: Leg, plants: list[Plant], locks: Locks, grot: Tensor, gpos: Tensor, local_rot: Tensor) -> LegPlan:
    """The goals of ``leg`` (module doc, step 3): the locks inside the plants, and around them the copy's own
    motion plus the lock's offset at the plant's edge, faded out by a smoothstep."""
    frames = gpos.shape[0]
    target = gpos[:, leg.ankle].clone()
    foot_rot = grot[:, leg.ankle].clone()
    toe_local = local_rot[:, leg.toe].clone() if leg.toe >= 0 else None
    driven = torch.zeros(frames, dtype=torch.bool)
    inside = torch.zeros(frames, dtype=torch.bool)
    target[locks.frames] = locks.ankle
    foot_rot[locks.frames] = locks.foot_rotation
    if toe_local is not None and locks.toe_local is not None:
        toe_local[locks.frames] = locks.toe_local
    driven[locks.frames] = True
    inside[locks.frames] = True
    ramp_f, ramp_w, ramp_e = [], [], []
    for p in plants:
        for i in range(1, p.ramp_in + 1):
            ramp_f.append(p.start - i)
            ramp_w.append(1.0 - i / (p.ramp_in + 1))
            ramp_e.append(p.start)
        for i in range(1, p.ramp_out + 1):
            ramp_f.append(p.stop + i)
            ramp_w.append(1.0 - i / (p.ramp_out + 1))
            ramp_e.append(p.stop)
    if ramp_f:
        f_idx, e_idx = torch.tensor(ramp_f), torch.tensor(ramp_e)
        w = smoothstep(torch.tensor(ramp_w, dtype=gpos.dtype))
        n = len(ramp_f)
        target[f_idx] = gpos[f_idx, leg.ankle] + w[:, None] * (target[e_idx] - gpos[e_idx, leg.ankle])
        delta = rot.mul(foot_rot[e_idx], rot.inv(grot[e_idx, leg.ankle]))
        foot_rot[f_idx] = rot.mul(_slerp(rot.identity(n, dtype=delta.dtype), delta, w), grot[f_idx, leg.ankle])
        if toe_local is not None:
            d_toe = rot.mul(toe_local[e_idx], rot.inv(local_rot[e_idx, leg.toe]))
            toe_local[f_idx] = rot.mul(_slerp(rot.identity(n, dtype=d_toe.dtype), d_toe, w), local_rot[f_idx, leg.toe])
        driven[f_idx] = True
    return LegPlan(target, rot.normalize(foot_rot), toe_local, driven, inside)


def _dilate_smooth(x: Tensor, radius: int) -> Tensor:
    """``x (F,)`` dilated (running max over +-radius) then averaged with a Hann window of the same support:
    smooth, and never below ``x`` where ``x >= 0``."""
    if radius <= 0 or x.numel() == 0:
        return x
    pad = torch.nn.functional.pad(x[None, None], (radius, radius), value=0.0)
    dil = torch.nn.functional.max_pool1d(pad, 2 * radius + 1, stride=1)
    win = torch.hann_window(2 * radius + 3, periodic=False)[1:-1]
    win = (win / win.sum()).view(1, 1, -1)
    return torch.nn.functional.conv1d(torch.nn.functional.pad(dil, (radius, radius)), win).view(-1)


def pelvis_drop(
    legs: list[Leg], plans: list[LegPlan], gpos: Tensor, params: FootLockParams, scale: float, radius: int
) -> Tensor:
    """``(F,)`` how far the pelvis goes down (m) so every driven leg reaches its target within the reach."""
    need = torch.zeros(gpos.shape[0])
    for leg, plan in zip(legs, plans, strict=True):
        hip, knee, ankle = gpos[:, leg.hip], gpos[:, leg.knee], gpos[:, leg.ankle]
        full = (knee - hip).norm(dim=-1) + (ankle - knee).norm(dim=-1)
        reach = params.max_reach * full * 0.999  # a hair inside the IK clamp
        v = hip - plan.target
        horizontal2 = v[:, 0] ** 2 + v[:, 2] ** 2
        room = (reach**2 - horizontal2).clamp_min(0.0).sqrt()
        drop = torch.where(horizontal2 < reach**2, v[:, 1] - room, v[:, 1])
        need = torch.maximum(need, torch.where(plan.driven, drop.clamp_min(0.0), torch.zeros_like(drop)))
    need = need.clamp_max(params.max_pelvis_drop_m * scale)
    return _dilate_smooth(need, radius) if bool((need > 0).any()) else need


def free_foot_heights(
    leg: Leg, plan: LegPlan, model: FootModel, rest_translations: Tensor
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """On the frames outside ``leg``'s plants, ``idx (M,)``: its lowest foot vertex ``(M,)`` and its toe joint
    ``(M,)`` (0: the ankle without toes) above the ankle target, from the planned foot pose and the rigid foot
    model (it matches skinning to 1 mm on the shared bodies)."""
    idx = torch.nonzero(~plan.inside).flatten()
    foot_rot = plan.foot_rotation[idx]
    low = (_up_row(foot_rot) @ model.local[~model.on_toe].T).amin(-1)
    toe_y = torch.zeros_like(low)
    if leg.toe >= 0:
        toe_y = (_up_row(foot_rot) * rest_translations[leg.toe]).sum(-1)
    if plan.toe_local is not None and leg.toe >= 0 and bool(model.on_toe.any()):
        toe_world = rot.mul(foot_rot, plan.toe_local[idx])
        low = torch.minimum(low, toe_y + (_up_row(toe_world) @ model.local[model.on_toe].T).amin(-1))
    return idx, low, toe_y


def floor_lift(
    leg: Leg, plan: LegPlan, model: FootModel, drop: Tensor, rest_translations: Tensor, blend: int,
    least_toe_y: Tensor | None = None, body_lift: Tensor | None = None,
) -> Tensor:  # fmt: skip
    """``(F,)`` how far to raise the ankle target on the frames outside its plants (the ramps, where the pelvis
    moved, and a free foot) so that the foot's lowest vertex stays above the floor (a dancer's foot the copy
    dips under it) and its toe joint (the ankle without toes) no lower than ``least_toe_y (F,)`` (a foot the
    source holds off the floor stays as far off it), less ``body_lift (F,)``, what the whole body rises there
    (:func:`body_floor_lift`); spread over ``blend`` frames each side so it rises and sets smoothly."""
    if bool(plan.inside.all()):
        return torch.zeros_like(drop)
    idx, low, toe_y = free_foot_heights(leg, plan, model, rest_translations)
    body = torch.zeros_like(drop) if body_lift is None else body_lift.to(drop.dtype)
    # The spread lift fades in over the blend away from each plant (0 inside): spreading a later depth back to
    # the plant's edge would raise the foot in one frame there. Never below the floor depth itself, which starts
    # near 0 at the edge (the ramp leaves from the lock); the toe's shortfall is faded in the same way (a foot
    # leaving a flat lock is below a source toe that left the floor already).
    taper = smoothstep(_frames_from(plan.inside).to(drop.dtype) / (blend + 1))
    under = torch.zeros_like(drop)
    under[idx] = (-(plan.target[idx, 1] + low) - body[idx]).clamp_min(0.0)
    if least_toe_y is not None:
        short = (least_toe_y[idx] - (plan.target[idx, 1] + toe_y) - body[idx]).clamp_min(0.0)
        under[idx] = torch.maximum(under[idx], taper[idx] * short)
    if not bool((under > 0).any()):
        return under
    lift = torch.maximum(under, taper * _dilate_smooth(under, blend))
    return torch.where(plan.inside, torch.zeros_like(lift), lift)


def body_floor_lift(
    legs: list[Leg], plans: list[LegPlan], models: list[FootModel], rest_translations: Tensor, scale: float,
    fps: float, params: FootLockParams,
) -> Tensor:  # fmt: skip
    """``(F,)`` how far the whole body rises where the free feet sink below the floor and no foot is planted: the
    floor stage's least-jerk lift (:func:`retarget_core.refine.floor.least_jerk_lift`, its settings), held at 0
    on every planted frame. Lifting the body moves no foot against the hips (the judged end-effector error), so
    the legs lift only what the body cannot. The depth left to the body fades in over ``body_lift_fade_seconds``
    from each plant: a body held down at a plant and asked to clear a deep foot just after it rises in a bump
    far higher than the foot (18 cm for a 4 cm dip without the fade, built case)."""
    floor = FloorParams()
    frames = plans[0].inside.shape[0]
    depth = torch.zeros(frames, dtype=torch.float64)
    for leg, plan, model in zip(legs, plans, models, strict=True):
        idx, low, _ = free_foot_heights(leg, plan, model, rest_translations)
        depth[idx] = torch.maximum(depth[idx], (-(plan.target[idx, 1] + low)).double())
    depth = torch.where(depth > floor.sunk_m * scale, depth, 0.0)
    if not bool((depth > 0).any()):
        return torch.zeros(frames, dtype=plans[0].target.dtype)
    planted = torch.stack([plan.inside for plan in plans], 0).any(0)
    fade = max(params.body_lift_fade_seconds * fps, 1.0)
    depth = depth * smoothstep(_frames_from(planted).double() / fade)
    ceiling = torch.where(planted, 0.0, torch.inf).double()
    lift = least_jerk_lift(torch.minimum(depth, ceiling), ceiling, fps, floor.size_weight)
    return lift.to(plans[0].target.dtype)


def least_toe_heights(
    ctx: RefineContext, legs: list[Leg], rest_pos: Tensor, scale: float, frames: int, params: FootLockParams
) -> list[Tensor | None]:  # fmt: skip
    """Per leg, ``(F,)`` the lowest height (m) its toe joint (the ankle without toes) may take: as far above its
    rest height as the source's toe stands above its own (``ctx.toe_heights``, at 1.80 m), at most
    ``params.free_toe_height_m``, scaled to the body; None where the source's heights are unknown."""
    if ctx.toe_heights is None:
        return [None for _ in legs]
    heights = ctx.toe_heights[:frames].to(rest_pos.dtype).cpu().clamp_max(params.free_toe_height_m)
    return [rest_pos[leg.toe if leg.toe >= 0 else leg.ankle, 1] + heights[:, k] * scale for k, leg in enumerate(legs)]


def _frames_from(inside: Tensor) -> Tensor:
    """``(F,)`` frames from each frame to the nearest frame of ``inside (F,)`` (0 there; large when none)."""
    at = torch.nonzero(inside).flatten()
    frames = torch.arange(inside.shape[0])
    if at.numel() == 0:
        return torch.full_like(frames, inside.shape[0] + 1)
    nearest = torch.searchsorted(at, frames).clamp(max=at.numel() - 1)
    before = at[(nearest - 1).clamp_min(0)]
    return torch.minimum((at[nearest] - frames).abs(), (frames - before).abs())


def apply_plans(
    motion: Motion, grot: Tensor, gpos: Tensor, root: int, legs: list[Leg], plans: list[LegPlan], drop: Tensor,
    lift: list[Tensor], params: FootLockParams, rest_rot: Tensor,
) -> tuple[Motion, Tensor, Tensor]:  # fmt: skip
    """The motion with the pelvis lowered by ``drop (F,)`` (raised where negative) and each leg solved to its
    plan (plus ``lift`` (F,) per leg on its target's height) on the frames it is driven or the pelvis moved;
    ``root``: the joint whose translation carries the pelvis. ``grot, gpos (F, J, .)``: the input's world
    transforms. Returns the motion and its world rotations and positions (only the legs are recomputed)."""
    sk = motion.skeleton
    local_r = motion.rotations.clone()
    local_t = motion.translations.clone()
    local_t[:, root, 1] -= drop
    down = torch.stack([torch.zeros_like(drop), drop, torch.zeros_like(drop)], -1)[:, None, :]
    new_pos = gpos - down
    new_rot = grot.clone()
    forward = torch.tensor(REST_FORWARD, dtype=gpos.dtype)
    for leg, plan, up in zip(legs, plans, lift, strict=True):
        idx = torch.nonzero(plan.driven | (drop != 0) | (up > 0)).flatten()
        if idx.numel() == 0:
            continue
        target = plan.target[idx].clone()
        target[:, 1] += up[idx]
        a_rot, b_rot = grot[idx, leg.hip], grot[idx, leg.knee]
        pole = rot.apply(rot.mul(b_rot, rot.inv(rest_rot[leg.knee])), forward.expand(len(idx), 3))
        new_a, new_b = two_bone_ik(
            new_pos[idx, leg.hip], new_pos[idx, leg.knee], new_pos[idx, leg.ankle], target, pole, a_rot, b_rot,
            params.max_reach,
        )  # fmt: skip
        delta_a = rot.mul(new_a, rot.inv(a_rot))
        delta_b = rot.mul(new_b, rot.inv(b_rot))
        local_r[idx, leg.hip] = rot.normalize(rot.mul(rot.inv(grot[idx, sk.parents[leg.hip]]), new_a))
        knee_parent = rot.mul(delta_a, grot[idx, sk.parents[leg.knee]])
        local_r[idx, leg.knee] = rot.normalize(rot.mul(rot.inv(knee_parent), new_b))
        ankle_parent = rot.mul(delta_b, grot[idx, sk.parents[leg.ankle]])
        local_r[idx, leg.ankle] = rot.normalize(rot.mul(rot.inv(ankle_parent), plan.foot_rotation[idx]))
        if plan.toe_local is not None and leg.toe >= 0:
            local_r[idx, leg.toe] = plan.toe_local[idx]
        # World transforms of the leg again (forward kinematics over the leg's joints on the solved frames).
        for j in subtree(sk.parents, leg.hip):
            par = sk.parents[j]
            r = rot.mul(new_rot[idx, par], local_r[idx, j])
            new_pos[idx, j] = new_pos[idx, par] + rot.apply(new_rot[idx, par], local_t[idx, j])
            new_rot[idx, j] = r
    return Motion(sk, motion.fps, local_r, local_t, motion.name), new_rot, new_pos


def _horizontal_speed(gpos: Tensor, joints: list[int], fps: float) -> Tensor:
    """``(F, len(joints))`` horizontal distance moved since the previous frame, per 1/30 s (0 on frame 0)."""
    p = gpos[:, joints][..., [0, 2]]
    out = torch.zeros(p.shape[:2])
    if p.shape[0] > 1:
        out[1:] = (p[1:] - p[:-1]).norm(dim=-1) * (fps / REFERENCE_FPS)
    return out


def slide_figures(gpos: Tensor, fps: float, legs: list[Leg], planted: list[Tensor], to_cm: float) -> dict[str, float | None]:
    """Mean and max horizontal toe/ankle speed on planted frames (cm per 1/30 s at 1.80 m) from world
    positions ``(F, J, 3)``."""
    vals = []
    for leg, p in zip(legs, planted, strict=True):
        joints = [leg.ankle] + ([leg.toe] if leg.toe >= 0 else [])
        speed = _horizontal_speed(gpos, joints, fps).mean(-1)
        both = p.clone()
        both[0] = False
        vals.append(speed[both])
    allv = torch.cat(vals) if vals else torch.zeros(0)
    if allv.numel() == 0:
        return {"mean": None, "max": None}
    return {"mean": round(float(allv.mean()) * to_cm, 4), "max": round(float(allv.max()) * to_cm, 4)}


def leg_penetration(ctx: RefineContext, motion: Motion, frames: Tensor, params: FootLockParams) -> dict[str, Any]:
    """Leg vertices against the other leg and the arms on ``frames`` (what moving the legs can change; arm
    vertices inside a leg are not tested: the leg vertices around them are inside the arm too): the deepest
    penetration (cm at 1.80 m), the frames deeper than 1 cm and the mean count of penetrating vertices."""
    to_cm = REFERENCE_HEIGHT_M / ctx.target.height * 100.0
    empty = {"frames": 0, "max_depth_cm": 0.0, "frames_over_1cm": 0, "penetrating_vertices_mean": 0.0}
    if frames.numel() == 0:
        return empty
    parts = ctx.parts
    cl = torch.tensor(parts.cluster)
    legs = (cl == CLUSTERS.index("left_leg")) | (cl == CLUSTERS.index("right_leg"))
    arms = (cl == CLUSTERS.index("left_arm")) | (cl == CLUSTERS.index("right_arm"))
    other = cl[:, None] != cl[None, :]
    allowed = ctx.sdf.allowed & other & legs[:, None] & (legs | arms)[None, :]
    grot, gpos = motion.global_transforms()
    grot, gpos = grot[frames], gpos[frames]
    with torch.no_grad():
        # Only leg vertices are tested: pose those alone.
        leg = legs[parts.vertex_part] if parts.body is None else legs[parts.vertex_part] & parts.body
        index = torch.nonzero(leg).flatten()
        posed = ctx.target.pose_vertex_subset(index, grot, gpos)
        mats = segment_matrices(ctx.target, parts, grot, gpos)
        samples = sample_pairs(ctx.sdf, posed, mats, allowed, vertices=index, inside_only=True)
        depth = effective_depth(ctx.sdf, samples)
    f_n = int(frames.numel())
    frame_max = torch.zeros(f_n).scatter_reduce(0, samples.frame, depth, "amax", include_self=True)
    tol = params.penetration_tolerance_m * ctx.target.height / REFERENCE_HEIGHT_M
    v_n = ctx.target.num_vertices
    deep = samples.frame[depth > tol] * v_n + samples.vertex[depth > tol]
    counts = torch.bincount(torch.unique(deep) // v_n, minlength=f_n) if deep.numel() else torch.zeros(f_n)
    return {
        "frames": f_n,
        "max_depth_cm": round(float(frame_max.max()) * to_cm, 3),
        "frames_over_1cm": int((frame_max * to_cm > 1.0).sum()),
        "penetrating_vertices_mean": round(float(counts.float().mean()), 2),
    }


@computes_on_cpu
def run(ctx: RefineContext, motion: Motion, params: FootLockParams | None = None) -> StageOutcome:
    """Hold the source's plants on the floor (module doc). Returns the motion and a report: frames changed,
    plants locked, foot slide on planted frames before/after, pelvis lowered frames, frames a free foot was raised
    and the largest raise, leg penetration before/after (on the changed frames) and seconds."""
    params = params or FootLockParams()
    t0 = time.perf_counter()
    character = ctx.target
    sk = motion.skeleton
    scale = character.height / REFERENCE_HEIGHT_M
    to_cm = 100.0 / scale
    frames = motion.num_frames
    legs = legs_of(ctx)
    hips = ctx.target_mapping.joints["Hips"]
    root = ([hips, *sk.ancestors(hips)])[-1]
    planted = source_plants(ctx, legs, frames)
    blend = max(1, round(params.blend_seconds * motion.fps))
    radius = max(1, round(params.pelvis_smooth_seconds * motion.fps))
    all_plants = [make_plants(plant_spans(p), frames, blend) for p in planted]
    if not any(all_plants):
        report = _report(0, [0, 0], None, None, 0, 0.0, None, None, time.perf_counter() - t0, 0.0, torch.zeros(0))
        return StageOutcome(motion, report)
    with torch.no_grad():
        grot, gpos = motion.global_transforms()
        rest_rot, rest_pos = sk.rest_global()
        sk_rest = (rest_rot, rest_pos, sk.rest_translations)
        feet = foot_vertices_of(ctx.parts).sides()
        models = [foot_model(character, ctx, leg, v, rest_rot, rest_pos) for leg, v in zip(legs, feet, strict=True)]

        plans = []
        for k, leg in enumerate(legs):
            if all_plants[k]:
                locks = lock_leg(leg, all_plants[k], models[k], grot, gpos, sk_rest, params, scale)
                plans.append(plan_leg(leg, all_plants[k], locks, grot, gpos, motion.rotations))
            else:
                plans.append(_idle_plan(leg, grot, gpos, motion.rotations))
        drop = pelvis_drop(legs, plans, gpos, params, scale, radius)
        least = least_toe_heights(ctx, legs, rest_pos, scale, frames, params)
        body = body_floor_lift(legs, plans, models, sk.rest_translations, scale, motion.fps, params)
        # A free foot rises with the body, and by its leg for what the body does not give.
        lifts = [
            floor_lift(leg, plan, model, drop, sk.rest_translations, blend, low, body)
            + torch.where(plan.inside, 0.0, body)
            for leg, plan, model, low in zip(legs, plans, models, least, strict=True)
        ]
        out, _, out_pos = apply_plans(motion, grot, gpos, root, legs, plans, drop - body, lifts, params, rest_rot)
        lock_seconds = time.perf_counter() - t0
        changed = ((out.rotations - motion.rotations).abs().amax(dim=(1, 2)) > 1e-6) | (
            (out.translations - motion.translations).abs().amax(dim=(1, 2)) > 1e-7
        )
        slide_before = slide_figures(gpos, motion.fps, legs, planted, to_cm)
        slide_after = slide_figures(out_pos, motion.fps, legs, planted, to_cm)
    changed_idx = torch.nonzero(changed).flatten()
    t1 = time.perf_counter()
    pen_before = pen_after = None
    if params.check_collisions:
        pen_before = leg_penetration(ctx, motion, changed_idx, params)
        pen_after = leg_penetration(ctx, out, changed_idx, params)
    check_seconds = time.perf_counter() - t1
    report = _report(
        int(changed.sum()), [len(p) for p in all_plants], slide_before, slide_after,
        int((drop > 1e-5).sum()), float(drop.max()) * to_cm, pen_before, pen_after, lock_seconds, check_seconds,
        torch.stack(lifts, 1) * to_cm if lifts else torch.zeros(0),
    )  # fmt: skip
    report["body_lifted_frames"] = int((body > 1e-5).sum())
    report["body_max_lift_cm"] = round(float(body.max()) * to_cm, 3) if body.numel() else 0.0
    return StageOutcome(out, report)


def _idle_plan(leg: Leg, grot: Tensor, gpos: Tensor, local_rot: Tensor) -> LegPlan:
    """A leg without plants: its goals are where the input has it (solved only where the pelvis moves)."""
    frames = gpos.shape[0]
    none = torch.zeros(frames, dtype=torch.bool)
    toe = local_rot[:, leg.toe].clone() if leg.toe >= 0 else None
    return LegPlan(gpos[:, leg.ankle].clone(), grot[:, leg.ankle].clone(), toe, none, none.clone())


def _report(
    frames_changed: int, per_foot: list[int], slide_before: dict | None, slide_after: dict | None,
    pelvis_frames: int, pelvis_max_cm: float, pen_before: dict | None, pen_after: dict | None,
    lock_seconds: float, check_seconds: float, lift_cm: Tensor,
) -> dict[str, Any]:  # fmt: skip
    """The stage's report; ``lift_cm (F, legs)``: each free foot's raise (over the floor, or to the source's toe
    height) in cm at 1.80 m."""
    return {
        "frames_changed": frames_changed,
        "plants_locked": sum(per_foot),
        "plants_per_foot": {"left": per_foot[0], "right": per_foot[1]},
        "foot_slide_before_cm_per_frame": slide_before,
        "foot_slide_after_cm_per_frame": slide_after,
        "pelvis_lowered_frames": pelvis_frames,
        "pelvis_max_drop_cm": round(pelvis_max_cm, 3),
        "feet_lifted_frames": int((lift_cm > 1e-3).any(dim=1).sum()) if lift_cm.numel() else 0,
        "feet_max_lift_cm": round(float(lift_cm.max()), 3) if lift_cm.numel() else 0.0,
        "leg_penetration_before": pen_before,
        "leg_penetration_after": pen_after,
        "seconds": round(lock_seconds + check_seconds, 4),
        "seconds_lock": round(lock_seconds, 4),
        "seconds_collision_check": round(check_seconds, 4),
        "units": "lengths in cm at a 1.80 m character, speeds per 1/30 s",
    }


__all__ = ["FootLockParams", "leg_penetration", "plant_spans", "run", "source_plants"]
