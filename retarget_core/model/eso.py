"""Encoder-space optimisation (paper 1, section 3.3 and appendix B), batched over the clip.

The network's encoder states ``h_enc (1, F, H)`` are optimised (as offsets on knots every ``knot_frames``
frames, linearly interpolated: smooth by construction) against the energy with relaxed weights, only on the
frames whose constraints are not met (and a few frames around them, faded in and out, so the decoder's
recurrence carries the change smoothly):

- a frame is flagged when one of its contact constraints is farther than ``met_m`` but within the 15 cm gate
  (farther contacts are left alone: the network's output says the shape does not let the hand get there), or
  when a sentinel vertex is deeper than ``penetration_m`` inside another part;
- contact term: each gated hand vertex is pulled toward ``0.7 x its position at the round's start + 0.3 x the
  contact vertex`` (the paper's smooth step); ``rounds`` rounds restart the step from where it got to, so the
  gap shrinks by about 0.7 per round;
- the joints the hands touch (the touched vertex's segment joint) are held near the network's output;
- interpenetration on "sentinel" vertices (one per ~4 cm surface cluster, ~10x fewer than the mesh) for the
  inner loop and the final check: the result is kept only when the energy (contact + sentinel
  interpenetration) on the flagged frames went down;
- skeleton terms (rotations, root and end-effector velocities) against the network's output on every frame
  optimised, and planted foot joints held where the network put them.
The root is not optimised (the paper does): translating the body changes neither self-contacts nor
self-penetration, only the feet, which the foot-lock stage after this one owns.
Adam (beta1 0.5, lr 0.01) as the paper; the paper runs 30 steps per frame one frame at a time, we run
``rounds x steps`` over all flagged frames at once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.energy.sdf import (  # _sample_grid: the grid lookup alone, for the cached pairs
    REFERENCE_HEIGHT_M,
    PairSamples,
    PartSDF,
    _sample_grid,
    effective_depth,
    sample_pairs,
    vertex_clusters,
)
from retarget_core.energy.terms import UNIT_AREA_M2
from retarget_core.geometry.point_poser import RowPlan, pose_rows
from retarget_core.kinematics import forward_kinematics, linear_blend_skinning, skinning_matrices
from retarget_core.model import energy as en
from retarget_core.model.inference import NetworkInputs, decode_motion
from retarget_core.model.network import RecurrentRetargeter
from retarget_core.model.windowed_decode import DecodeWindows, plan_windows
from retarget_core.rotations import normalize as r_normalize


@dataclass(frozen=True)
class ESOParams:
    """Settings (lengths at a 1.80 m character, but ``gate_m`` and ``met_m``: on the body's own scale, as tuned;
    read at 1.80 m they cost two held-out misses, docs/collisions.md). Weights: the paper relaxes its training weights by
    rho 1000 -> 10, beta 100 -> 1, lambda 1000 -> 100; our training weights (rotation 100, interpenetration
    100, contact 1000) relaxed by the same factors give rotation 1, interpenetration 1, contact 100."""

    rounds: int = 3
    steps: int = 10
    learning_rate: float = 0.01
    adam_betas: tuple[float, float] = (0.5, 0.999)
    gate_m: float = 0.15  # paper: contacts optimised only when within 15 cm (body's own metres)
    met_m: float = 0.01  # a contact closer than 1 cm is met (body's own metres)
    penetration_m: float = 0.01  # a frame penetrates when a sentinel vertex is 1 cm deep (the acceptance's frames > 1 cm)
    step_share: float = 0.3  # paper: target = 0.7 x current + 0.3 x contact vertex
    fade_frames: int = 4  # flagged frames' neighbours optimised with a linear fade over this many frames
    sentinel_cluster_m: float = 0.04
    pair_keep_m: float = 0.01  # pairs closer than 1 cm (or inside) at the start are the ones the loop samples
    w_rotation: float = 1.0
    w_root: float = 1.0
    w_end_effector: float = 1.0
    w_interpenetration: float = 1.0
    w_contact: float = 100.0
    w_hold: float = 100.0
    w_foot: float = 100.0  # planted foot joints held near the network's output (m^2 at 1.80 m), as the hands' targets
    knot_frames: int = 6  # state offsets live on knots this far apart (0.2 s at 30 fps)
    w_smooth: float = 1000.0  # the change's own jerk: third differences of its joint moves (m^2 at 1.80 m)


@dataclass
class Sentinels:
    """A vertex subset with its own small SDF view: index ``(N,)`` and a PartSDF whose per-vertex tables are
    restricted to it (areas scaled so sums stay comparable with the full mesh)."""

    index: Tensor
    sdf: PartSDF
    weights: Tensor
    vertices: Tensor


def sentinels(kit: en.BodyKit, cluster_m: float = 0.04) -> Sentinels:
    """One vertex per rest-pose cluster of ``cluster_m`` (at 1.80 m) of each part."""
    sdf = kit.sdf
    rest = kit.character.vertices.float()
    size = cluster_m * kit.height / REFERENCE_HEIGHT_M
    cl = vertex_clusters(rest, sdf.parts.vertex_part, size)
    first = cl.members[:, 0]
    idx = torch.sort(first[first >= 0]).values
    if sdf.parts.body is not None:
        idx = idx[sdf.parts.body[idx]]  # accessories are never sentinels
    parts = replace(sdf.parts, vertex_part=sdf.parts.vertex_part[idx], weights=sdf.parts.weights[idx], body=None)
    sub_rest = rest[idx]
    scale = float(sdf.vertex_area.sum() / sdf.vertex_area[idx].sum().clamp_min(1e-12))
    sub = replace(
        sdf, parts=parts, rest_depth=sdf.rest_depth[idx], geodesic_weight=sdf.geodesic_weight[idx],
        vertex_area=sdf.vertex_area[idx] * scale,
        clusters=vertex_clusters(sub_rest, parts.vertex_part, 2 * size),
    )  # fmt: skip
    return Sentinels(idx, sub, kit.weights[idx], sub_rest)


def _int_energy(sdf: PartSDF, posed: Tensor, seg_mats: Tensor) -> tuple[Tensor, Tensor]:
    """E_int ``(N,)`` and the deepest weighted depth ``(N,)`` (m, this body's scale) per frame."""
    samples = sample_pairs(sdf, posed, seg_mats)
    depth = effective_depth(sdf, samples)
    s = sdf.scale_to_180
    area = sdf.vertex_area.to(posed.dtype).index_select(0, samples.vertex) * s * s / UNIT_AREA_M2
    energy = posed.new_zeros(posed.shape[0]).index_add(0, samples.frame, area * (depth * s).pow(2))
    deepest = posed.new_zeros(posed.shape[0]).scatter_reduce(0, samples.frame, depth.detach(), "amax")
    return energy, deepest


@dataclass
class PairCache:
    """Sentinel (frame, vertex, part) pairs found once by the broad phase, grouped by part: the inner loop
    samples only these grids (the culling of :func:`sample_pairs` costs more than the sampling)."""

    frame: Tensor
    vertex: Tensor
    groups: list[tuple[int, Tensor]]


def cache_pairs(sdf: PartSDF, posed: Tensor, seg_mats: Tensor, keep_m: float) -> PairCache:
    """Pairs whose signed distance is below ``keep_m`` (m, this body's scale) now: the ones that penetrate
    or may come to during the optimisation."""
    with torch.no_grad():
        smp = sample_pairs(sdf, posed, seg_mats)
        keep = smp.distance < keep_m
    frame, vertex, part = smp.frame[keep], smp.vertex[keep], smp.part[keep]
    order = torch.argsort(part, stable=True)
    frame, vertex, part = frame[order], vertex[order], part[order]
    groups = [(int(j), torch.nonzero(part == j).flatten()) for j in torch.unique(part).tolist()]
    return PairCache(frame, vertex, groups)


def cached_energy(sdf: PartSDF, x: Tensor, seg_mats: Tensor, cache: PairCache) -> Tensor:
    """E_int ``(N,)`` of the cached pairs' posed sentinels ``x (M, 3)`` (:func:`_skin_cached`) on frames whose
    segment transforms are ``seg_mats (N, S, 3, 4)`` (differentiable)."""
    if cache.frame.numel() == 0:
        return seg_mats.new_zeros(seg_mats.shape[0])
    dist = []
    part = torch.empty_like(cache.frame)
    for j, sel in cache.groups:
        f = cache.frame[sel]
        r, t = seg_mats[f, j, :, :3], seg_mats[f, j, :, 3]
        local = torch.einsum("nji,nj->ni", r, x[sel] - t)
        dist.append(_sample_grid(sdf, j, local))
        part[sel] = j
    smp = PairSamples(cache.frame, cache.vertex, part, torch.cat(dist))
    depth = effective_depth(sdf, smp) * sdf.scale_to_180
    area = sdf.vertex_area.to(x.dtype).index_select(0, cache.vertex) * sdf.scale_to_180**2 / UNIT_AREA_M2
    return x.new_zeros(seg_mats.shape[0]).index_add(0, cache.frame, area * depth.pow(2))


def _row_plan(sent: Sentinels, cache: PairCache, num_joints: int) -> RowPlan:
    """What :func:`pose_rows` needs to skin just the cached pairs' sentinels: each row's nonzero influences."""
    k = max(int((sent.weights > 0).sum(1).max()), 1) if len(sent.weights) else 1
    weight, joint = sent.weights.index_select(0, cache.vertex).topk(k, dim=1)
    return RowPlan((cache.frame[:, None] * num_joints + joint).reshape(-1), weight,
                   sent.vertices.index_select(0, cache.vertex))  # fmt: skip


def _skin_cached(kit: en.BodyKit, plan: RowPlan, grot: Tensor, gpos: Tensor) -> tuple[Tensor, Tensor]:
    """The cached pairs' posed sentinels ``(M, 3)`` and the segments' skinning transforms ``(N, S, 3, 4)`` of
    frames ``grot (N, J, 4)``, ``gpos (N, J, 3)``: only the rows the energy reads are skinned."""
    mats = skinning_matrices(kit.rest_rot, kit.rest_pos, grot, gpos)
    return pose_rows(plan, mats), mats[:, torch.tensor(kit.parts.joints, dtype=torch.long)]


def _skin_sentinels(kit: en.BodyKit, sent: Sentinels, grot: Tensor, gpos: Tensor) -> tuple[Tensor, Tensor]:
    """Posed sentinels ``(N, V', 3)`` and the segments' skinning transforms ``(N, S, 3, 4)`` (one set of
    joint matrices serves both)."""
    mats = skinning_matrices(kit.rest_rot, kit.rest_pos, grot, gpos)
    seg = mats[:, torch.tensor(kit.parts.joints, dtype=torch.long)]
    return linear_blend_skinning(sent.vertices, sent.weights, mats), seg


def _fade(flags: Tensor, frames: int) -> Tensor:
    """Weights ``(F,)``: 1 on flagged frames, falling linearly to 0 over ``frames`` frames around them."""
    w = flags.float()
    if frames <= 0 or not bool(flags.any()):
        return w
    t = torch.arange(flags.shape[0], dtype=torch.float32)
    dist = (t[:, None] - t[flags][None, :]).abs().min(dim=1).values
    return (1.0 - dist / (frames + 1)).clamp_min(0.0)


@dataclass
class ESOResult:
    rotations: Tensor
    translations: Tensor
    report: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Start:
    """The network's motion and what it leaves unmet. rot ``(F, J, 4)``, trans and gpos ``(F, J, 3)``;
    posed sentinels ``(F, V', 3)`` and their segment transforms ``(F, S, 3, 4)``; e_int ``(F,)`` their
    interpenetration energy; pen_flag ``(F,)`` frames deeper than ``penetration_m``; d0 ``(M,)`` contact
    distances (m), gated ``(M,)`` the ones optimised, and their frame, i, j ``(C,)``."""

    rot: Tensor
    trans: Tensor
    gpos: Tensor
    sent: Sentinels
    posed: Tensor
    mats: Tensor
    e_int: Tensor
    pen_flag: Tensor
    d0: Tensor
    gated: Tensor
    c_frame: Tensor
    c_i: Tensor
    c_j: Tensor


def _start(
    model: RecurrentRetargeter, kit: en.BodyKit, inputs: NetworkInputs, states: Tensor, embedding: Tensor,
    constraints: ContactConstraints, p: ESOParams,
) -> _Start:  # fmt: skip
    """Decode the network's motion ``states (1, F, H)`` and find its penetrating frames and gated contacts."""
    s = REFERENCE_HEIGHT_M / kit.height
    with torch.no_grad():
        rot0, trans0 = decode_motion(model, inputs, states, embedding)
        grot0, gpos0 = forward_kinematics(kit.rig.skeleton.parents, rot0, trans0)
    sent = sentinels(kit, p.sentinel_cluster_m)
    with torch.no_grad():
        posed0, mats0 = _skin_sentinels(kit, sent, grot0, gpos0)
        e_int0, deep0 = _int_energy(sent.sdf, posed0, mats0)
        pen_flag = deep0 * s > p.penetration_m
        if constraints.count:
            d0 = en.contact_distance2(kit, grot0, gpos0, constraints.frame, constraints.i, constraints.j).sqrt()
            gated = (d0 > p.met_m) & (d0 <= p.gate_m)
        else:
            d0 = torch.zeros(0)
            gated = torch.zeros(0, dtype=torch.bool)
    return _Start(rot0, trans0, gpos0, sent, posed0, mats0, e_int0, pen_flag, d0, gated,
                  constraints.frame[gated], constraints.i[gated], constraints.j[gated])  # fmt: skip


def _knot_weights(last: int, knot_frames: int) -> Tensor:
    """Uniform cubic B-spline weights ``(last, K)`` from control knots every ``knot_frames`` frames (one more
    either side of the span) to frames ``0 .. last - 1``: state offsets live on the knots so the result is
    smooth by construction (per-frame offsets jitter), with continuous second differences (knots joined by
    straight lines put a kink, a jerk spike, at every knot: issue 22 item 4)."""
    step = max(knot_frames, 1)
    u = torch.arange(last, dtype=torch.float32) / step
    seg = u.floor()
    s = u - seg
    basis = torch.stack([(1 - s) ** 3, 3 * s**3 - 6 * s**2 + 4, -3 * s**3 + 3 * s**2 + 3 * s + 1, s**3], dim=1) / 6
    k_n = (int(seg.max()) if last else 0) + 4
    interp = torch.zeros(last, k_n)
    rows = torch.arange(last)
    for j in range(4):  # frame t reads control knots seg .. seg + 3 (knot 0 lies one step before frame 0)
        interp[rows, seg.long() + j] = basis[:, j]
    return interp


@dataclass
class _Problem:
    """What the solve reads. flags ``(F,)`` frames flagged, opt_frames ``(P,)`` their indices; weight ``(F,)``
    the fade; active ``(A,)`` frames with a nonzero weight, w_act ``(A,)`` theirs; last: one past the last
    active frame; pen_a ``(P,)`` and c_a ``(C,)`` rows of the flagged frames and gated contacts among the
    active ones; hold_joint ``(C,)`` the joint each touched vertex follows; plan: how to skin the cached pairs'
    sentinels; windows: how the decoder runs over the active span (dec_inputs hold its frames only); interp
    ``(last, K)`` knots to frames; planted ``(A, 4)`` foot labels, foot_cols and foot_idx the feet the rig has."""

    model: RecurrentRetargeter
    kit: en.BodyKit
    start: _Start
    states: Tensor
    embedding: Tensor
    dec_inputs: NetworkInputs
    windows: DecodeWindows
    flags: Tensor
    opt_frames: Tensor
    weight: Tensor
    active: Tensor
    w_act: Tensor
    last: int
    pen_a: Tensor
    c_a: Tensor
    hold_joint: Tensor
    cache: PairCache
    plan: RowPlan
    interp: Tensor
    planted: Tensor
    foot_cols: list[int]
    foot_idx: Tensor


def _problem(
    model: RecurrentRetargeter, kit: en.BodyKit, inputs: NetworkInputs, states: Tensor, embedding: Tensor,
    st: _Start, flags: Tensor, feet: Tensor, p: ESOParams,
) -> _Problem:  # fmt: skip
    """The active window around the ``flags (F,)`` frames, the cached sentinel pairs and the held joints."""
    f_n = st.rot.shape[0]
    opt_frames = torch.nonzero(flags).flatten()
    weight = _fade(flags, p.fade_frames)
    active = torch.nonzero(weight > 0).flatten()
    last = int(active[-1]) + 1
    position = torch.full((f_n,), -1, dtype=torch.long)
    position[active] = torch.arange(active.numel())
    hold_joint = torch.tensor([kit.parts.joints[int(v)] for v in kit.parts.vertex_part[st.c_j]], dtype=torch.long)
    keep_m = p.pair_keep_m * kit.height / REFERENCE_HEIGHT_M
    with torch.no_grad():
        cache = cache_pairs(st.sent.sdf, st.posed[opt_frames], st.mats[opt_frames], keep_m)
    foot_cols = [c for c, j in enumerate(kit.foot_joints) if j >= 0]
    foot_idx = torch.tensor([kit.foot_joints[c] for c in foot_cols], dtype=torch.long)
    first = int(active[0])
    dec_inputs = NetworkInputs(kit.rig, inputs.features[:, first:last], inputs.heading[:, first:last],
                               inputs.copy_rot[:, first:last], inputs.copy_trans[:, first:last], inputs.code)  # fmt: skip
    windows = plan_windows(model, states[:, :last], embedding, first)
    return _Problem(
        model, kit, st, states, embedding, dec_inputs, windows, flags, opt_frames, weight, active, weight[active], last,
        position[opt_frames], position[st.c_frame], hold_joint, cache, _row_plan(st.sent, cache, kit.rest_rot.shape[0]),
        _knot_weights(last, p.knot_frames),
        feet[active].float(), foot_cols, foot_idx,
    )  # fmt: skip


def _evaluate(pb: _Problem, dh: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Local rotations ``(A, J, 4)``, translations, global rotations and positions of the active frames for knot
    offsets ``dh (1, K, H)``: the optimised output blended into the network's by the fade weight (frames past
    the window keep the network's output, whatever the recurrence would carry there)."""
    st = pb.start
    rot0_a, trans0_a = st.rot[pb.active], st.trans[pb.active]
    offset = torch.einsum("tk,bkh->bth", pb.interp, dh)
    last = pb.last
    rot, trans = decode_motion(pb.model, pb.dec_inputs, pb.states[:, :last] + pb.weight[None, :last, None] * offset,
                               pb.embedding, pb.windows)  # fmt: skip
    local = pb.active - pb.windows.first
    r = rot[local]
    r = torch.where((r * rot0_a).sum(-1, keepdim=True) < 0, -r, r)  # nlerp (slerp's acos has no gradient at 1)
    rot = r_normalize(rot0_a + pb.w_act[:, None, None] * (r - rot0_a))
    trans = trans0_a + pb.w_act[:, None, None] * (trans[local] - trans0_a)
    grot, gpos = forward_kinematics(pb.kit.rig.skeleton.parents, rot, trans)
    return rot, trans, grot, gpos


def _contact_goal(pb: _Problem, p: ESOParams, dh: Tensor) -> Tensor:
    """Where each gated hand vertex ``(C, 3)`` is pulled this round: the paper's smooth step from where it is
    now toward the contact vertex."""
    st, kit = pb.start, pb.kit
    with torch.no_grad():
        _, _, grot_r, gpos_r = _evaluate(pb, dh)
        xi0 = en.vertex_positions(kit, grot_r, gpos_r, pb.c_a, st.c_i) if len(st.c_i) else torch.zeros(0, 3)
        xj0 = en.vertex_positions(kit, grot_r, gpos_r, pb.c_a, st.c_j) if len(st.c_j) else torch.zeros(0, 3)
        return (1 - p.step_share) * xi0 + p.step_share * xj0


def _loss(pb: _Problem, p: ESOParams, dh: Tensor, goal: Tensor) -> Tensor:
    """The relaxed energy (a scalar) of knot offsets ``dh (1, K, H)``: skeleton terms against the network's
    output, planted feet held, sentinel interpenetration, hands toward ``goal (C, 3)``, touched joints held."""
    st, kit = pb.start, pb.kit
    s = REFERENCE_HEIGHT_M / kit.height
    gpos0_a = st.gpos[pb.active]
    rot, _, grot, gpos = _evaluate(pb, dh)
    sk = en.skeleton_terms(kit, rot, st.rot[pb.active], gpos, gpos0_a)
    loss = (
        p.w_rotation * sk["rotation"].sum() + p.w_root * sk["root"].sum() + p.w_end_effector * sk["end_effector"].sum()
    )
    if pb.foot_cols:
        drift = ((gpos[:, pb.foot_idx] - gpos0_a[:, pb.foot_idx]) * s).pow(2).sum(-1)
        loss = loss + p.w_foot * (pb.planted[:, pb.foot_cols] * drift).sum()
    loss = loss + p.w_smooth * _change_jerk(pb, gpos, gpos0_a, s)
    e_int = cached_energy(st.sent.sdf, *_skin_cached(kit, pb.plan, grot[pb.pen_a], gpos[pb.pen_a]), pb.cache)
    loss = loss + p.w_interpenetration * e_int.sum()
    if len(st.c_i):
        xi = en.vertex_positions(kit, grot, gpos, pb.c_a, st.c_i)
        loss = loss + p.w_contact * ((xi - goal) * s).pow(2).sum(-1).sum()
        held = gpos[pb.c_a, pb.hold_joint] - st.gpos[st.c_frame, pb.hold_joint]
        loss = loss + p.w_hold * (held * s).pow(2).sum(-1).sum()
    return loss


def _change_jerk(pb: _Problem, gpos: Tensor, gpos0_a: Tensor, s: float) -> Tensor:
    """The summed squared third differences (per frame, at 1.80 m) of the joints' moves ``gpos - gpos0_a (A, J,
    3)`` on the active frames, zero elsewhere: the change itself rises and sets smoothly, wherever it is made."""
    move = gpos.new_zeros(pb.last, *gpos.shape[1:])
    move = move.index_put((pb.active,), (gpos - gpos0_a) * s)
    if pb.last < 4:
        return move.new_zeros(())
    return (move[3:] - 3 * move[2:-1] + 3 * move[1:-2] - move[:-3]).pow(2).sum()


def _solve(pb: _Problem, p: ESOParams) -> Tensor:
    """Knot offsets ``(1, K, H)`` of the encoder states after ``rounds x steps`` Adam steps."""
    dh = torch.zeros(1, pb.interp.shape[1], pb.states.shape[-1], requires_grad=True)
    opt = torch.optim.Adam([dh], lr=p.learning_rate, betas=p.adam_betas)
    for _ in range(max(p.rounds, 0)):
        goal = _contact_goal(pb, p, dh)
        for _ in range(p.steps):
            loss = _loss(pb, p, dh, goal)
            opt.zero_grad()
            loss.backward()
            opt.step()
    return dh


@dataclass
class _Check:
    """The solved motion ``(F, J, 4)``, ``(F, J, 3)`` and the energy that decides whether it is kept: the
    sentinels' interpenetration on the flagged frames ``(P,)`` before and after, contact distances after
    ``(C,)`` (m), and the totals."""

    rot: Tensor
    trans: Tensor
    before_int: Tensor
    after_int: Tensor
    d1: Tensor
    e_before: float
    e_after: float


def _check(pb: _Problem, p: ESOParams, dh: Tensor) -> _Check:
    """Pose the solution and compare the energy (contact + sentinel interpenetration) with the start's. The
    check uses the sentinels too (the full mesh costs ~10x more); the metrics measure the full mesh."""
    st, kit = pb.start, pb.kit
    with torch.no_grad():
        rot_a, trans_a, grot, gpos = _evaluate(pb, dh)
        before_int = st.e_int[pb.opt_frames]
        after_int, _ = _int_energy(st.sent.sdf, *_skin_sentinels(kit, st.sent, grot[pb.pen_a], gpos[pb.pen_a]))
        d1 = en.contact_distance2(kit, grot, gpos, pb.c_a, st.c_i, st.c_j).sqrt() if len(st.c_i) else torch.zeros(0)
        e_before = float(before_int.sum()) + p.w_contact * float(st.d0[st.gated].pow(2).sum())
        e_after = float(after_int.sum()) + p.w_contact * float(d1.pow(2).sum())
        rot, trans = st.rot.clone(), st.trans.clone()
        rot[pb.active], trans[pb.active] = rot_a, trans_a
    return _Check(rot, trans, before_int, after_int, d1, e_before, e_after)


def _ms_per_frame(started: float, frames: int) -> float:
    return round(1000 * (time.perf_counter() - started) / max(frames, 1), 3)


def _solved_report(pb: _Problem, p: ESOParams, ck: _Check, kept: bool) -> dict[str, Any]:
    """The report fields of a solve: frames, energies and contact distances before and after (cm)."""
    st = pb.start
    has = bool(len(st.c_i))
    moved = (st.d0[st.gated] - ck.d1) * 100 if has else torch.zeros(0)
    return dict(
        frames_optimised=int(pb.flags.sum()), frames_touched=int(pb.active.numel()), iterations=p.rounds * p.steps,
        kept=bool(kept), energy_before=round(ck.e_before, 5), energy_after=round(ck.e_after, 5),
        interpenetration_before=round(float(ck.before_int.sum()), 5),
        interpenetration_after=round(float(ck.after_int.sum()), 5),
        contact_cm_before=round(float(st.d0[st.gated].mean()) * 100, 3) if has else None,
        contact_cm_after=round(float(ck.d1.mean()) * 100, 3) if has else None,
        constraint_moved_cm=[round(float(x), 2) for x in moved[:200]],
    )  # fmt: skip


def optimise(
    model: RecurrentRetargeter, kit: en.BodyKit, inputs: NetworkInputs, states: Tensor, embedding: Tensor,
    constraints: ContactConstraints, feet: Tensor, params: ESOParams | None = None,
) -> ESOResult:  # fmt: skip
    """ESO of one clip. ``states (1, F, H)``, ``embedding (1, E)`` from the network; ``feet (F, 4)`` planted
    labels. Returns the refined local rotations ``(F, J, 4)`` and translations ``(F, J, 3)``."""
    p = params or ESOParams()
    started = time.perf_counter()
    st = _start(model, kit, inputs, states, embedding, constraints, p)
    f_n = st.rot.shape[0]
    d0, gated = st.d0, st.gated
    flags = st.pen_flag.clone()
    flags[st.c_frame] = True
    report: dict[str, Any] = {
        "frames_flagged_penetration": int(st.pen_flag.sum()), "contacts_gated": int(gated.sum()),
        "contacts_beyond_gate": int((d0 > p.gate_m).sum()), "contacts_already_met": int((d0 <= p.met_m).sum()),
    }  # fmt: skip
    if not bool(flags.any()):
        report.update(frames_optimised=0, kept=False, ms_per_frame=_ms_per_frame(started, f_n))
        return ESOResult(st.rot, st.trans, report)
    pb = _problem(model, kit, inputs, states, embedding, st, flags, feet, p)
    ck = _check(pb, p, _solve(pb, p))
    kept = ck.e_after < ck.e_before
    report.update(_solved_report(pb, p, ck, kept), ms_per_frame=_ms_per_frame(started, f_n))
    if not kept:
        return ESOResult(st.rot, st.trans, report)
    return ESOResult(ck.rot.detach(), ck.trans.detach(), report)


__all__ = ["ESOParams", "ESOResult", "Sentinels", "optimise", "sentinels"]
