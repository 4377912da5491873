"""Encoder-space optimisation (paper 1, section 3.3 and appendix B), batched over the clip.

The network's encoder states ``h_enc (1, F, H)`` are optimised (as offsets on knots every ``knot_frames``
frames, linearly interpolated: smooth by construction) against the energy with relaxed weights, only on the frames whose constraints are not met (and a few frames around them, faded
in and out, so the decoder's recurrence carries the change smoothly):

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
from retarget_core.kinematics import forward_kinematics, linear_blend_skinning, skinning_matrices
from retarget_core.model import energy as en
from retarget_core.model.inference import NetworkInputs, decode_motion
from retarget_core.model.network import RecurrentRetargeter
from retarget_core.rotations import normalize as r_normalize


@dataclass(frozen=True)
class ESOParams:
    """Settings (lengths at a 1.80 m character). Weights: the paper relaxes its training weights by
    rho 1000 -> 10, beta 100 -> 1, lambda 1000 -> 100; our training weights (rotation 100, interpenetration
    100, contact 1000) relaxed by the same factors give rotation 1, interpenetration 1, contact 100."""

    rounds: int = 3
    steps: int = 10
    learning_rate: float = 0.01
    adam_betas: tuple[float, float] = (0.5, 0.999)
    gate_m: float = 0.15  # paper: contacts optimised only when within 15 cm
    met_m: float = 0.01  # a contact closer than 1 cm is met
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


def cached_energy(sdf: PartSDF, posed: Tensor, seg_mats: Tensor, cache: PairCache) -> Tensor:
    """E_int ``(N,)`` of posed sentinels ``(N, V', 3)`` on the cached pairs only (differentiable)."""
    if cache.frame.numel() == 0:
        return posed.new_zeros(posed.shape[0])
    x = posed.reshape(-1, 3).index_select(0, cache.frame * posed.shape[1] + cache.vertex)
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
    area = sdf.vertex_area.to(posed.dtype).index_select(0, cache.vertex) * sdf.scale_to_180**2 / UNIT_AREA_M2
    return posed.new_zeros(posed.shape[0]).index_add(0, cache.frame, area * depth.pow(2))


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


def optimise(
    model: RecurrentRetargeter, kit: en.BodyKit, inputs: NetworkInputs, states: Tensor, embedding: Tensor,
    constraints: ContactConstraints, feet: Tensor, params: ESOParams | None = None,
) -> ESOResult:  # fmt: skip
    """ESO of one clip. ``states (1, F, H)``, ``embedding (1, E)`` from the network; ``feet (F, 4)`` planted
    labels. Returns the refined local rotations ``(F, J, 4)`` and translations ``(F, J, 3)``."""
    p = params or ESOParams()
    start = time.perf_counter()
    rig = kit.rig
    parents = rig.skeleton.parents
    s = REFERENCE_HEIGHT_M / kit.height
    with torch.no_grad():
        rot0, trans0 = decode_motion(model, inputs, states, embedding)
        grot0, gpos0 = forward_kinematics(parents, rot0, trans0)
    f_n = rot0.shape[0]
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
    c_frame, c_i, c_j = constraints.frame[gated], constraints.i[gated], constraints.j[gated]
    flags = pen_flag.clone()
    flags[c_frame] = True
    report: dict[str, Any] = {
        "frames_flagged_penetration": int(pen_flag.sum()), "contacts_gated": int(gated.sum()),
        "contacts_beyond_gate": int((d0 > p.gate_m).sum()), "contacts_already_met": int((d0 <= p.met_m).sum()),
    }  # fmt: skip
    if not bool(flags.any()):
        report.update(frames_optimised=0, kept=False, ms_per_frame=round(1000 * (time.perf_counter() - start) / max(f_n, 1), 3))
        return ESOResult(rot0, trans0, report)
    opt_frames = torch.nonzero(flags).flatten()
    weight = _fade(flags, p.fade_frames)
    active = torch.nonzero(weight > 0).flatten()
    w_act = weight[active]
    last = int(active[-1]) + 1
    position = torch.full((f_n,), -1, dtype=torch.long)
    position[active] = torch.arange(active.numel())
    pen_a, c_a = position[opt_frames], position[c_frame]
    hold_joint = torch.tensor([kit.parts.joints[int(v)] for v in kit.parts.vertex_part[c_j]], dtype=torch.long)
    rot0_a, trans0_a, gpos0_a = rot0[active], trans0[active], gpos0[active]
    with torch.no_grad():
        cache = cache_pairs(sent.sdf, posed0[opt_frames], mats0[opt_frames], p.pair_keep_m * kit.height / REFERENCE_HEIGHT_M)
    # State offsets on knots every knot_frames frames, linearly interpolated: smooth by construction (per-frame
    # offsets made the result jitter: jerk ratio 2.4 on a held-out clip in our first run).
    knots = torch.arange(0, last + p.knot_frames, p.knot_frames).clamp(max=max(last - 1, 0)).unique()
    t = torch.arange(last, dtype=torch.float32)
    seg = torch.searchsorted(knots.float(), t, right=True).clamp(1, max(len(knots) - 1, 1)) - 1
    k0, k1 = knots[seg].float(), knots[(seg + 1).clamp(max=len(knots) - 1)].float()
    frac = ((t - k0) / (k1 - k0).clamp_min(1.0)).clamp(0, 1)
    interp = torch.zeros(last, len(knots))
    interp[torch.arange(last), seg] = 1 - frac
    interp[torch.arange(last), (seg + 1).clamp(max=len(knots) - 1)] += frac
    dh = torch.zeros(1, len(knots), states.shape[-1], requires_grad=True)
    opt = torch.optim.Adam([dh], lr=p.learning_rate, betas=p.adam_betas)
    planted = feet[active].float()  # (A, 4) planted foot joints are held where the network put them
    foot_cols = [c for c, j in enumerate(kit.foot_joints) if j >= 0]
    foot_idx = torch.tensor([kit.foot_joints[c] for c in foot_cols], dtype=torch.long)
    dec_inputs = NetworkInputs(rig, inputs.features[:, :last], inputs.heading[:, :last], inputs.copy_rot[:, :last],
                               inputs.copy_trans[:, :last], inputs.code)  # fmt: skip

    def evaluate() -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The active frames ``(A, ...)``: the optimised output blended into the network's by the fade weight
        (frames past the window keep the network's output, whatever the recurrence would carry there)."""
        offset = torch.einsum("tk,bkh->bth", interp, dh)
        rot, trans = decode_motion(model, dec_inputs, states[:, :last] + weight[None, :last, None] * offset, embedding)
        r = rot[active]
        r = torch.where((r * rot0_a).sum(-1, keepdim=True) < 0, -r, r)  # nlerp (slerp's acos has no gradient at 1)
        rot = r_normalize(rot0_a + w_act[:, None, None] * (r - rot0_a))
        trans = trans0_a + w_act[:, None, None] * (trans[active] - trans0_a)
        grot, gpos = forward_kinematics(parents, rot, trans)
        return rot, trans, grot, gpos

    for _ in range(max(p.rounds, 0)):
        with torch.no_grad():
            _, _, grot_r, gpos_r = evaluate()
            xi0 = en.vertex_positions(kit, grot_r, gpos_r, c_a, c_i) if len(c_i) else torch.zeros(0, 3)
            xj0 = en.vertex_positions(kit, grot_r, gpos_r, c_a, c_j) if len(c_j) else torch.zeros(0, 3)
            goal = (1 - p.step_share) * xi0 + p.step_share * xj0
        for _ in range(p.steps):
            rot, trans, grot, gpos = evaluate()
            sk = en.skeleton_terms(kit, rot, rot0_a, gpos, gpos0_a)
            loss = p.w_rotation * sk["rotation"].sum() + p.w_root * sk["root"].sum() + p.w_end_effector * sk["end_effector"].sum()
            if foot_cols:
                drift = ((gpos[:, foot_idx] - gpos0_a[:, foot_idx]) * s).pow(2).sum(-1)
                loss = loss + p.w_foot * (planted[:, foot_cols] * drift).sum()
            e_int = cached_energy(sent.sdf, *_skin_sentinels(kit, sent, grot[pen_a], gpos[pen_a]), cache)
            loss = loss + p.w_interpenetration * e_int.sum()
            if len(c_i):
                xi = en.vertex_positions(kit, grot, gpos, c_a, c_i)
                loss = loss + p.w_contact * ((xi - goal) * s).pow(2).sum(-1).sum()
                held = gpos[c_a, hold_joint] - gpos0[c_frame, hold_joint]
                loss = loss + p.w_hold * (held * s).pow(2).sum(-1).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        rot_a, trans_a, grot, gpos = evaluate()
        # The check uses the sentinels too (the full mesh costs ~10x more); metrics measure the full mesh.
        before_int = e_int0[opt_frames]
        after_int, _ = _int_energy(sent.sdf, *_skin_sentinels(kit, sent, grot[pen_a], gpos[pen_a]))
        d1 = en.contact_distance2(kit, grot, gpos, c_a, c_i, c_j).sqrt() if len(c_i) else torch.zeros(0)
        e_before = float(before_int.sum()) + p.w_contact * float(d0[gated].pow(2).sum())
        e_after = float(after_int.sum()) + p.w_contact * float(d1.pow(2).sum())
        rot, trans = rot0.clone(), trans0.clone()
        rot[active], trans[active] = rot_a, trans_a
    kept = e_after < e_before
    moved = (d0[gated] - d1) * 100 if len(c_i) else torch.zeros(0)
    report.update(
        frames_optimised=int(flags.sum()), frames_touched=int(active.numel()), iterations=p.rounds * p.steps,
        kept=bool(kept), energy_before=round(e_before, 5), energy_after=round(e_after, 5),
        interpenetration_before=round(float(before_int.sum()), 5), interpenetration_after=round(float(after_int.sum()), 5),
        contact_cm_before=round(float(d0[gated].mean()) * 100, 3) if len(c_i) else None,
        contact_cm_after=round(float(d1.mean()) * 100, 3) if len(c_i) else None,
        constraint_moved_cm=[round(float(x), 2) for x in moved[:200]],
        ms_per_frame=round(1000 * (time.perf_counter() - start) / max(f_n, 1), 3),
    )  # fmt: skip
    if not kept:
        return ESOResult(rot0, trans0, report)
    return ESOResult(rot.detach(), trans.detach(), report)


__all__ = ["ESOParams", "ESOResult", "Sentinels", "optimise", "sentinels"]
