"""The collision resolver's energy on a subset of points, batched over frames (one value for the whole clip).

Points: "sentinel" vertices (one per small rest-pose cluster on the hands, arms, legs and head, a few hundred)
plus the contact vertices; the finishing pass adds every vertex found penetrating. Each point is tested only
against the segments it may reach: candidate (frame, point, segment) triples are chosen once on the input pose,
with slack for the motion the optimiser makes (:func:`candidate_triples`).

Terms (lengths in cm at a 1.80 m character, so the weights mean the same on every body):
- penetration: ``sum geodesic_weight * relu(depth - tolerance)^2`` with ``depth`` the blended-SDF depth beyond the
  bind pose's; the tolerance is ``-clearance`` for a collision (pushed a little outside) and ``+contact
  tolerance`` for a hand in the part it touches (a contact is a target, not a collision);
- contact: ``relu(d - gap)^2`` with ``d`` the signed distance of a contact's nearest hand point to the part it
  touches (nearest segment of that part's cluster): a hand that left the surface is pulled back within ``gap``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS
from retarget_core.energy.sdf import PartSDF, segment_distance, vertex_clusters

SENTINEL_CLUSTERS: tuple[str, ...] = ("head", "torso", "left_arm", "right_arm", "left_leg", "right_leg")


def sentinel_vertices(sdf: PartSDF, rest_vertices: Tensor, cell_m: float, segments: list[int] | None = None) -> Tensor:
    """``(P,)`` vertex indices: per rest-pose cell of edge ``cell_m`` (body scale) and part of the
    :data:`SENTINEL_CLUSTERS` (or of ``segments`` when given), the vertex nearest the cell's centroid."""
    parts = sdf.parts
    if segments is None:
        keep_cluster = torch.tensor([CLUSTERS[c] in SENTINEL_CLUSTERS for c in parts.cluster])
    else:
        keep_cluster = torch.zeros(parts.num_parts, dtype=torch.bool)
        keep_cluster[segments] = True
    vc = vertex_clusters(rest_vertices, parts.vertex_part, cell_m, max_members=64)
    c_n = vc.part.shape[0]
    counts = torch.bincount(vc.of_vertex, minlength=c_n).to(rest_vertices.dtype)
    centre = torch.zeros(c_n, 3, dtype=rest_vertices.dtype).index_add_(0, vc.of_vertex, rest_vertices) / counts[:, None]
    d = (rest_vertices - centre[vc.of_vertex]).norm(dim=-1)
    best = torch.full((c_n,), float("inf"), dtype=d.dtype).scatter_reduce(0, vc.of_vertex, d, "amin")
    is_best = d <= best[vc.of_vertex]
    idx = torch.nonzero(is_best).flatten()
    # One vertex per cell (ties: the first).
    _, first = torch.unique(vc.of_vertex[idx], return_inverse=True)
    chosen = torch.zeros(int(first.max()) + 1 if len(first) else 0, dtype=torch.long)
    chosen[first.flip(0)] = idx.flip(0)
    return chosen[keep_cluster[parts.vertex_part[chosen]]]


@dataclass
class TripleSet:
    """Candidate (frame, point, segment) triples grouped by segment.

    groups: per segment with candidates, ``(seg, frame (N,), point (N,), tolerance (N,) m, weight (N,),
    rest_depth (N,) m)``; frames index the optimised frames, points the point set."""

    groups: list[tuple[int, Tensor, Tensor, Tensor, Tensor, Tensor]]

    @property
    def count(self) -> int:
        return sum(len(g[1]) for g in self.groups)


def candidate_triples(sdf: PartSDF, points: Tensor, posed: Tensor, seg_mats: Tensor, frames: Tensor,
                      exempt: Tensor, allowed: Tensor, slack: float | Tensor, clearance: float,
                      contact_tolerance: float, only_penetrating: bool = False,
                      contact_weight: float = 1.0, hold: Tensor | None = None) -> TripleSet:  # fmt: skip
    """Triples for point vertices ``points (P,)`` posed ``(Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``
    at clip frames ``frames (Fa,)``: every allowed segment whose grid box, grown by ``slack``, holds the point
    and whose distance is below ``slack`` (m, or ``(P,)`` per point). ``exempt (F, S, 6)``: segment-of-point x cluster pairs in contact
    per clip frame (their tolerance is ``contact_tolerance``, their weight times ``contact_weight``: the hand is
    brought to the surface by the contact term, the sunk part only nudged out). ``only_penetrating``: keep
    depths > 0 only. ``hold (C, C)`` bool, point cluster x segment cluster (:data:`CLUSTERS`): pairs kept no
    deeper than on the given pose instead of pushed out (tolerance: the depth there, at least ``-clearance``)."""
    parts = sdf.parts
    part = parts.vertex_part.index_select(0, points)  # (P,)
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    lo = sdf.origin
    hi = lo + (sdf.size - 1).to(lo.dtype) * sdf.voxel[:, None]
    groups = []
    f_a, p_n = posed.shape[:2]
    slack_p = torch.as_tensor(slack, dtype=posed.dtype).expand(p_n)
    with torch.no_grad():
        for j in range(parts.num_parts):
            if sdf.grids[j] is None:
                continue
            ok_p = allowed[part, j]
            if not bool(ok_p.any()):
                continue
            p_idx = torch.nonzero(ok_p).flatten()
            r, t = seg_mats[:, j, :, :3], seg_mats[:, j, :, 3]  # (Fa, 3, 3), (Fa, 3)
            x = posed[:, p_idx]  # (Fa, n, 3)
            local = torch.einsum("fji,fnj->fni", r, x - t[:, None])
            out = (local - torch.maximum(torch.minimum(local, hi[j]), lo[j])).norm(dim=-1)
            f_i, n_i = torch.nonzero(out <= slack_p[p_idx][None], as_tuple=True)
            if len(f_i) == 0:
                continue
            d = segment_distance(sdf, j, local[f_i, n_i])
            pt = p_idx[n_i]
            rest = sdf.rest_depth[points[pt], j]
            keep = (-d - rest > 0.0) if only_penetrating else d < slack_p[pt]
            f_i, pt, rest = f_i[keep], pt[keep], rest[keep]
            if len(f_i) == 0:
                continue
            ex = exempt[frames[f_i], part[pt], cluster[j]]
            tol = torch.where(ex, torch.full_like(rest, contact_tolerance), torch.full_like(rest, -clearance))
            if hold is not None and bool(hold[cluster[part[pt]], cluster[j]].any()):
                held = hold[cluster[part[pt]], cluster[j]]
                tol = torch.where(held, torch.maximum(tol, -d[keep] - rest), tol)
            weight = sdf.geodesic_weight[points[pt], j] * torch.where(ex, contact_weight, 1.0)
            groups.append((j, f_i, pt, tol, weight, rest))
    return TripleSet(groups)


def to_segment(mats: Tensor, x: Tensor) -> Tensor:
    """Points ``x (N, 3)`` taken back to their segments' rest frames by the rigid transforms ``mats (N, 3, 4)``."""
    return torch.einsum("nji,nj->ni", mats[..., :3], x - mats[..., 3])


def group_depth(sdf: PartSDF, seg: int, x: Tensor, mats: Tensor, rest: Tensor) -> Tensor:
    """Depth ``(N,)`` (m) of posed points ``x (N, 3)`` in segment ``seg`` (transforms ``mats (N, 3, 4)``) beyond
    the bind pose's ``rest (N,)`` (negative outside)."""
    return -segment_distance(sdf, seg, to_segment(mats, x)) - rest


def gather_rows(posed: Tensor, seg_mats: Tensor, frame: Tensor, point: Tensor, seg: int) -> tuple[Tensor, Tensor]:
    """Posed points ``(N, 3)`` of ``posed (Fa, P, 3)`` and segment ``seg``'s transforms ``(N, 3, 4)`` of
    ``seg_mats (Fa, S, 3, 4)`` at the rows ``frame (N,)``, ``point (N,)``."""
    x = posed.reshape(-1, 3).index_select(0, frame * posed.shape[1] + point)
    return x, seg_mats[:, seg].index_select(0, frame)


def triple_depths(sdf: PartSDF, triples: TripleSet, posed: Tensor, seg_mats: Tensor) -> list[Tensor]:
    """Per group of ``triples``, the depth ``(N,)`` (m) of each triple's point in its segment beyond the
    bind pose's (negative outside)."""
    return [group_depth(sdf, j, *gather_rows(posed, seg_mats, f_i, pt, j), rest)
            for j, f_i, pt, _tol, _weight, rest in triples.groups]  # fmt: skip


def penetration_energy_rows(sdf: PartSDF, triples: TripleSet, xs: list[Tensor], mats: list[Tensor],
                            scale: float) -> Tensor:  # fmt: skip
    """Sum over triples of ``weight * relu(depth - tolerance)^2`` in cm^2 at 1.80 m (a scalar), from each group's
    posed points ``xs[k] (N, 3)`` and segment transforms ``mats[k] (N, 3, 4)``."""
    total = xs[0].new_zeros(()) if xs else torch.zeros(())
    for (j, _, _, tol, weight, rest), x, m in zip(triples.groups, xs, mats, strict=True):
        pen = (group_depth(sdf, j, x, m, rest) - tol).clamp_min(0.0) * (100.0 * scale)
        total = total + (weight * pen.pow(2)).sum()
    return total


def penetration_energy(sdf: PartSDF, triples: TripleSet, posed: Tensor, seg_mats: Tensor, scale: float) -> Tensor:
    """:func:`penetration_energy_rows` on ``posed (Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``."""
    rows = [gather_rows(posed, seg_mats, f_i, pt, j) for j, f_i, pt, *_ in triples.groups]
    return penetration_energy_rows(sdf, triples, [r[0] for r in rows], [r[1] for r in rows], scale)


def near_triples(sdf: PartSDF, triples: TripleSet, posed: Tensor, seg_mats: Tensor, within: float) -> TripleSet:
    """The triples whose point is deeper than ``-within`` (m) at the given pose: the only ones whose
    penetration term can become non-zero during the next few steps (no gradients)."""
    groups = []
    with torch.no_grad():
        for g, depth in zip(triples.groups, triple_depths(sdf, triples, posed, seg_mats), strict=True):
            keep = depth > -within
            if bool(keep.any()):
                groups.append((g[0], *(x[keep] for x in g[1:])))
    return TripleSet(groups)  # type: ignore[arg-type]


@dataclass
class ContactTargets:
    """Hands to keep on (or bring to) the surface of the part they touch: contact instance ``k`` is met when the
    nearest of its hand's points lies on the surface of its touched cluster.

    frame, point, cluster, instance: ``(N,)`` per (instance, hand point) pair: optimised-frame index, index into
    the point set, touched cluster, instance index; active: ``(K,)`` 1 where the instance starts within reach;
    segments: per cluster index, its segments with grids."""

    frame: Tensor
    point: Tensor
    cluster: Tensor
    instance: Tensor
    active: Tensor
    segments: dict[int, list[int]]
    gap: Tensor | None = None  # (K,) m: each instance is met within this of its part (None: contact_energy's gap)
    tested: list[tuple[int, Tensor]] | None = None  # per segment, the pair rows measured against it (None: every
    # row against every segment of its cluster; :func:`near_contact_rows` keeps the ones that can be the nearest)

    @property
    def count(self) -> int:
        return int(self.active.shape[0])

    def segment_rows(self) -> list[tuple[int, Tensor]]:
        """Per segment ``j``, the pair rows ``(n,)`` whose distance to ``j`` is measured."""
        if self.tested is not None:
            return self.tested
        out: list[tuple[int, Tensor]] = []
        for c, segs in self.segments.items():
            sel = torch.nonzero(self.cluster == c).flatten()
            if len(sel):
                out.extend((j, sel) for j in segs)
        return out


def contact_row_points(targets: ContactTargets) -> list[tuple[int, Tensor, Tensor, Tensor]]:
    """Per measured segment ``j``: ``(j, rows (n,), frame (n,), point (n,))`` of the pair rows measured against it."""
    return [(j, sel, targets.frame.index_select(0, sel), targets.point.index_select(0, sel))
            for j, sel in targets.segment_rows()]  # fmt: skip


def contact_distances_rows(sdf: PartSDF, targets: ContactTargets, xs: list[Tensor],
                           mats: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """Signed distances ``(M,)`` (m) of the measured (pair row, segment) combinations, their rows and segments
    ``(M,)``, from the posed points ``xs[k] (n, 3)`` and transforms ``mats[k] (n, 3, 4)`` of each
    :func:`contact_row_points` entry."""
    measured = targets.segment_rows()
    if not measured:
        e = torch.zeros(0, dtype=torch.long)
        return torch.zeros(0), e, e
    ds = [segment_distance(sdf, j, to_segment(m, x)) for (j, _), x, m in zip(measured, xs, mats, strict=True)]
    return torch.cat(ds), torch.cat([sel for _, sel in measured]), torch.cat([torch.full_like(sel, j) for j, sel in measured])


def _row_distances(sdf: PartSDF, targets: ContactTargets, posed: Tensor,
                   seg_mats: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """:func:`contact_distances_rows` on ``posed (Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``."""
    rows = [gather_rows(posed, seg_mats, f, pt, j) for j, _, f, pt in contact_row_points(targets)]
    d, r, s = contact_distances_rows(sdf, targets, [x for x, _ in rows], [m for _, m in rows])
    return d.to(posed.dtype), r, s


def nearest_per_instance(targets: ContactTargets, d: Tensor, rows: Tensor) -> Tensor:
    """``(K,)`` the smallest of the row distances ``d (M,)`` per contact instance (rows ``(M,)``)."""
    out = d.new_full((targets.count,), float("inf"))
    return out.scatter_reduce(0, targets.instance.index_select(0, rows), d, "amin", include_self=True)


def instance_distance(sdf: PartSDF, targets: ContactTargets, posed: Tensor, seg_mats: Tensor) -> Tensor:
    """``(K,)`` signed distance (m) of each contact instance's nearest hand point to its touched cluster."""
    d, rows, _ = _row_distances(sdf, targets, posed, seg_mats)
    return nearest_per_instance(targets, d, rows)


def near_contact_rows(sdf: PartSDF, targets: ContactTargets, posed: Tensor, seg_mats: Tensor,
                      within: float) -> ContactTargets:  # fmt: skip
    """``targets`` measuring only the (pair row, segment) combinations within ``within`` (m) of their
    instance's nearest at the given pose: the only ones that can become the nearest during the next few steps
    (no gradients; the same distances while they hold)."""
    with torch.no_grad():
        d, rows, seg_of = _row_distances(sdf, targets, posed, seg_mats)
        inst = targets.instance.index_select(0, rows)
        best = d.new_full((targets.count,), float("inf")).scatter_reduce(0, inst, d, "amin", include_self=True)
        keep = d <= best.index_select(0, inst) + within
    tested = [(j, rows[keep & (seg_of == j)]) for j in torch.unique(seg_of[keep]).tolist()]
    return replace(targets, tested=tested)


def contact_energy_rows(targets: ContactTargets, d: Tensor, rows: Tensor, scale: float, gap: float = 0.0) -> Tensor:
    """Sum of ``relu(d - gap)^2`` (cm^2 at 1.80 m) over the active contact instances (a scalar) from the row
    distances ``d (M,)`` of :func:`contact_distances_rows`: a hand farther than ``gap`` (m; ``targets.gap`` per
    instance when set) from the part it touches is pulled back within it."""
    if targets.count == 0:
        return d.new_zeros(())
    g: Tensor | float = targets.gap if targets.gap is not None else gap
    return (((nearest_per_instance(targets, d, rows) - g).clamp_min(0.0) * (100.0 * scale)).pow(2) * targets.active).sum()


def contact_energy(sdf: PartSDF, targets: ContactTargets, posed: Tensor, seg_mats: Tensor, scale: float,
                   gap: float = 0.0) -> Tensor:  # fmt: skip
    """:func:`contact_energy_rows` on ``posed (Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``."""
    if targets.count == 0:
        return posed.new_zeros(())
    d, rows, _ = _row_distances(sdf, targets, posed, seg_mats)
    return contact_energy_rows(targets, d, rows, scale, gap)


@dataclass
class ContactPairs:
    """The contact constraints' vertex pairs ``(N,)``: optimised-frame index, the two point indices, and their
    distance on the input (m): a pair may come closer, not drift apart (the hand stays where it touched)."""

    frame: Tensor
    i: Tensor
    j: Tensor
    input_distance: Tensor

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])


def pair_distance(pairs: ContactPairs, posed: Tensor) -> Tensor:
    """``(N,)`` distance (m) of each pair's two posed points."""
    flat = posed.reshape(-1, 3)
    base = pairs.frame * posed.shape[1]
    return (flat.index_select(0, base + pairs.i) - flat.index_select(0, base + pairs.j)).norm(dim=-1)


def pair_energy_rows(pairs: ContactPairs, xi: Tensor, xj: Tensor, scale: float, allowance: float) -> Tensor:
    """Sum of ``relu(d - d_input - allowance)^2`` (cm^2 at 1.80 m) over the pairs (a scalar) posed at
    ``xi, xj (N, 3)``."""
    grow = (xi - xj).norm(dim=-1) - pairs.input_distance - allowance
    return (grow.clamp_min(0.0) * (100.0 * scale)).pow(2).sum()


def pair_energy(pairs: ContactPairs, posed: Tensor, scale: float, allowance: float) -> Tensor:
    """:func:`pair_energy_rows` on ``posed (Fa, P, 3)``."""
    if pairs.count == 0:
        return posed.new_zeros(())
    flat = posed.reshape(-1, 3)
    base = pairs.frame * posed.shape[1]
    return pair_energy_rows(pairs, flat.index_select(0, base + pairs.i), flat.index_select(0, base + pairs.j), scale, allowance)


__all__ = [
    "ContactPairs",
    "contact_distances_rows",
    "contact_energy_rows",
    "contact_row_points",
    "gather_rows",
    "group_depth",
    "nearest_per_instance",
    "pair_energy_rows",
    "penetration_energy_rows",
    "to_segment",
    "pair_distance",
    "pair_energy",
    "ContactTargets",
    "SENTINEL_CLUSTERS",
    "TripleSet",
    "candidate_triples",
    "instance_distance",
    "contact_energy",
    "near_contact_rows",
    "near_triples",
    "penetration_energy",
    "triple_depths",
    "sentinel_vertices",
]
