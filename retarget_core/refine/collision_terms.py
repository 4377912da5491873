"""The collision energy's inputs for one set of points (:class:`Terms`): the poser of the points, the
(point, segment) triples that may collide, the contact targets and pairs, the posed-mesh pairs and the floor
points, as indices into the points; :func:`compact` keeps only the points in use."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS
from retarget_core.context import RefineContext
from retarget_core.geometry.point_poser import PointPoser, RowPlan, pose_rows
from retarget_core.geometry.triples import TripleSet, candidate_triples
from retarget_core.refine.collision_check import ContactInstances
from retarget_core.refine.collision_energy import (
    ContactPairs,
    ContactTargets,
    contact_row_points,
    instance_distance,
    pair_distance,
)
from retarget_core.refine.collision_mesh import MeshPairs, MeshTerms
from retarget_core.refine.collision_params import CollisionParams
from retarget_core.refine.collision_problem import Ground, Problem


@dataclass
class Terms:
    """The energy's inputs that depend on the point set."""

    poser: PointPoser
    triples: TripleSet
    targets: ContactTargets
    pairs: ContactPairs
    mesh: MeshTerms
    ground: GroundTerms


@dataclass
class GroundTerms:
    """Foot points kept above the floor, hands beside a planted foot too (else a floor of ``-inf``), per (frame,
    point) row ``(N,)``: ``frame`` optimised frame, ``point`` index into the poser's points, ``floor`` the height (m)
    it may not go below."""

    frame: Tensor
    point: Tensor
    floor: Tensor

    def select(self, keep: Tensor) -> GroundTerms:
        return GroundTerms(self.frame[keep], self.point[keep], self.floor[keep])


def contact_targets(ctx: RefineContext, contacts: ContactInstances, frames: Tensor, points: Tensor,
                     hand_points: Tensor | None = None) -> ContactTargets:  # fmt: skip
    """Contact instances of the optimised frames with their hand's points (indices into ``points``; only
    vertices of ``hand_points`` when given: the sentinels and contact vertices, a few per hand)."""
    pos_of = torch.full((ctx.num_frames,), -1, dtype=torch.long)
    pos_of[frames] = torch.arange(len(frames))
    point_part = ctx.parts.vertex_part.index_select(0, points)
    if hand_points is not None:
        eligible = torch.zeros(ctx.target.num_vertices, dtype=torch.bool)
        eligible[hand_points] = True
        point_part = torch.where(eligible[points], point_part, torch.full_like(point_part, -1))
    members = ctx.parts.cluster_members()
    segments = {ci: [s for s in members[name] if ctx.sdf.grids[s] is not None] for ci, name in enumerate(CLUSTERS)}
    # Per hand segment, its points (ascending, -1 padded): each kept instance gets one row per point of its hand.
    s_n = ctx.parts.num_parts
    owned = point_part[None, :] == torch.arange(s_n)[:, None]  # (S, P)
    counts = owned.sum(1)
    table = torch.full((s_n, max(int(counts.max()) if len(points) else 0, 1)), -1, dtype=torch.long)
    seg_of, col = torch.nonzero(owned, as_tuple=True)
    table[seg_of, torch.arange(len(seg_of)) - torch.cumsum(counts, 0)[seg_of] + counts[seg_of]] = col
    kept = torch.nonzero((pos_of[contacts.frame] >= 0) & (counts[contacts.hand] > 0)).flatten()
    pts = table.index_select(0, contacts.hand[kept])  # (K, maxP)
    valid = pts >= 0
    per = valid.sum(1)
    frame = pos_of[contacts.frame[kept]].repeat_interleave(per)
    cluster = contacts.cluster[kept].repeat_interleave(per)
    instance = torch.arange(len(kept)).repeat_interleave(per)
    gap = contacts.gap[kept] if contacts.gap is not None else None
    return ContactTargets(frame, pts[valid], cluster, instance, torch.ones(len(kept)), segments, gap)



def build_terms(ctx: RefineContext, prob: Problem, points: Tensor, contacts: ContactInstances, exempt: Tensor,
                 params: CollisionParams, scale: float, slack: float | Tensor, allowed: Tensor,
                 hand_points: Tensor | None = None, mesh: MeshPairs | None = None,
                 ground: Ground | None = None, select_local: Tensor | None = None) -> Terms:  # fmt: skip
    """Poser, candidate triples (segment pairs of ``allowed (S, S)`` within ``slack`` (m, or per point) on the
    input pose, or on ``select_local (Fa, J, 3, 3)`` when given: a pose the optimiser reached) and contact
    targets of a point set."""
    poser = PointPoser(ctx.target, points, ctx.parts.joints)
    with torch.no_grad():
        posed, seg_mats, _ = poser(prob.local_in, prob.trans)
        sel_posed, sel_mats = (posed, seg_mats) if select_local is None else poser(select_local, prob.trans)[:2]
    triples = candidate_triples(ctx.sdf, points, sel_posed, sel_mats, prob.frames, exempt, allowed,
                                slack, params.clearance_m / scale, params.contact_tolerance_m / scale,
                                contact_weight=params.contact_penetration_weight)  # fmt: skip
    targets = contact_targets(ctx, contacts, prob.frames, points, hand_points)
    if targets.count:
        with torch.no_grad():
            d0 = instance_distance(ctx.sdf, targets, posed, seg_mats)
        targets.active = (d0 < params.contact_reach_m / scale).float()
    pairs = contact_pairs(ctx, prob.frames, points)
    if pairs.count:
        with torch.no_grad():
            pairs.input_distance = pair_distance(pairs, posed)
    return Terms(poser, triples, targets, pairs, mesh_terms(ctx, mesh, prob.frames, points),
                  ground_terms(ctx, ground, prob.frames, points))


def ground_terms(ctx: RefineContext, ground: Ground | None, frames: Tensor, points: Tensor) -> GroundTerms:
    """The floor points of ``ground`` that are among ``points`` (indices into them), on every optimised frame."""
    e = torch.zeros(0, dtype=torch.long)
    if ground is None or len(ground.vertex) == 0:
        return GroundTerms(e, e, torch.zeros(0))
    point_of = torch.full((ctx.target.num_vertices,), -1, dtype=torch.long)
    point_of[points] = torch.arange(len(points))
    idx = point_of[ground.vertex]
    ok = torch.nonzero(idx >= 0).flatten()
    floor = ground.floor[frames][:, ok]  # (Fa, G)
    frame = torch.arange(len(frames)).repeat_interleave(len(ok))
    return GroundTerms(frame, idx[ok].repeat(len(frames)), floor.reshape(-1))


def near_ground(ground: GroundTerms, posed: Tensor, within: float) -> GroundTerms:
    """The floor rows whose point is less than ``within`` (m) above its floor on ``posed (Fa, P, 3)``: the only
    ones whose term can become non-zero during the next few steps."""
    y = posed[..., 1].reshape(-1).index_select(0, ground.frame * posed.shape[1] + ground.point)
    return ground.select(y - ground.floor < within)


def mesh_terms(ctx: RefineContext, mesh: MeshPairs | None, frames: Tensor, points: Tensor) -> MeshTerms:
    """The mesh pairs (clip frames) on the optimised ``frames`` whose vertex and triangle are all ``points``,
    as indices into the optimised frames and ``points``."""
    e = torch.zeros(0, dtype=torch.long)
    if mesh is None or mesh.count == 0:
        return MeshTerms(e, e, torch.zeros(0, 3, dtype=torch.long), torch.zeros(0))
    pos_of = torch.full((ctx.num_frames,), -1, dtype=torch.long)
    pos_of[frames] = torch.arange(len(frames))
    point_of = torch.full((ctx.target.num_vertices,), -1, dtype=torch.long)
    point_of[points] = torch.arange(len(points))
    f, v, t = pos_of[mesh.frame], point_of[mesh.vertex], point_of[mesh.tri]
    ok = (f >= 0) & (v >= 0) & (t >= 0).all(-1)
    return MeshTerms(f[ok], v[ok], t[ok], mesh.sign[ok])


def contact_pairs(ctx: RefineContext, frames: Tensor, points: Tensor) -> ContactPairs:
    """The constraints of the optimised frames whose two vertices are both points (indices into ``points``)."""
    c = ctx.constraints
    pos_of = torch.full((ctx.num_frames,), -1, dtype=torch.long)
    pos_of[frames] = torch.arange(len(frames))
    point_of = torch.full((ctx.target.num_vertices,), -1, dtype=torch.long)
    point_of[points] = torch.arange(len(points))
    if c.count == 0:
        e = torch.zeros(0, dtype=torch.long)
        return ContactPairs(e, e, e, torch.zeros(0))
    f, i, j = pos_of[c.frame], point_of[c.i], point_of[c.j]
    ok = (f >= 0) & (i >= 0) & (j >= 0)
    return ContactPairs(f[ok], i[ok], j[ok], torch.zeros(int(ok.sum())))


def compact(ctx: RefineContext, terms: Terms) -> Terms:
    """``terms`` with a poser of only the points its triples and contact targets use (indices remapped)."""
    t, pr, me, gr = terms.targets, terms.pairs, terms.mesh, terms.ground
    used = torch.unique(torch.cat([g[2] for g in terms.triples.groups] + [t.point, pr.i, pr.j, me.point, me.tri.flatten(), gr.point]))
    remap = torch.full((len(terms.poser.points),), -1, dtype=torch.long)
    remap[used] = torch.arange(len(used))
    poser = PointPoser(ctx.target, terms.poser.points[used], ctx.parts.joints)
    groups = [(g[0], g[1], remap[g[2]], *g[3:]) for g in terms.triples.groups]
    targets = ContactTargets(t.frame, remap[t.point], t.cluster, t.instance, t.active, t.segments, t.gap, t.tested)
    pairs = ContactPairs(pr.frame, remap[pr.i], remap[pr.j], pr.input_distance)
    mesh = MeshTerms(me.frame, remap[me.point], remap[me.tri], me.sign)
    return Terms(poser, TripleSet(groups), targets, pairs, mesh, GroundTerms(gr.frame, remap[gr.point], gr.floor))


@dataclass
class EnergyRows:
    """What one energy evaluation reads, in the order its terms read it: ``points`` the distinct (frame, point)
    rows to pose, ``point_index (N,)`` every term's rows into them, cut by ``point_sizes``; ``seg_rows (M,)``
    rows of the flattened skinning transforms ``(Fa * J, 12)`` of the segments the points are measured in, cut
    by ``seg_sizes``."""

    points: RowPlan
    point_index: Tensor
    point_sizes: list[int]
    seg_rows: Tensor
    seg_sizes: list[int]


def energy_rows(terms: Terms, num_joints: int) -> EnergyRows:
    """The rows of ``terms`` (transforms of ``num_joints`` joints): triple groups, contact segments, pairs
    (i, j), mesh pairs (point, triangle corners), floor points."""
    pts: list[tuple[Tensor, Tensor]] = []
    segs: list[tuple[Tensor, int]] = []
    for j, f_i, pt, *_ in terms.triples.groups:
        pts.append((f_i, pt))
        segs.append((f_i, j))
    for j, _, f, pt in contact_row_points(terms.targets):
        pts.append((f, pt))
        segs.append((f, j))
    pr, me, gr = terms.pairs, terms.mesh, terms.ground
    pts += [(pr.frame, pr.i), (pr.frame, pr.j), (me.frame, me.point)] + [(me.frame, me.tri[:, k]) for k in range(3)]
    pts.append((gr.frame, gr.point))
    p_n = len(terms.poser.points)
    key = torch.cat([f * p_n + p for f, p in pts])
    distinct, inverse = torch.unique(key, return_inverse=True)
    plan = terms.poser.plan(distinct // p_n, distinct % p_n, num_joints)
    seg_joint = terms.poser.seg_joints
    seg_rows = torch.cat([f * num_joints + seg_joint[j] for f, j in segs]) if segs else torch.zeros(0, dtype=torch.long)
    return EnergyRows(plan, inverse, [len(f) for f, _ in pts], seg_rows, [len(f) for f, _ in segs])


def read_rows(rows: EnergyRows, mats: Tensor) -> tuple[list[Tensor], list[Tensor]]:
    """The posed points ``(n_k, 3)`` and segment transforms ``(m_k, 3, 4)`` of ``rows`` from skinning transforms
    ``mats (Fa, J, 3, 4)``, in the terms' order."""
    x = pose_rows(rows.points, mats).index_select(0, rows.point_index)
    m = mats.reshape(-1, 12).index_select(0, rows.seg_rows).reshape(-1, 3, 4)
    return list(torch.split(x, rows.point_sizes)), list(torch.split(m, rows.seg_sizes))


__all__ = ["EnergyRows", "GroundTerms", "Terms", "build_terms", "compact", "energy_rows", "near_ground", "read_rows", "contact_pairs", "contact_targets", "ground_terms", "mesh_terms"]
