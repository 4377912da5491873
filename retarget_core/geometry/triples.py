"""Sentinel points and (frame, point, segment) triples in the body-part SDFs, batched over frames: which points
of a limb may collide with which segments on which frames, how deep they are beyond the bind pose, and the
penetration energy of a set of triples (lengths in cm at a 1.80 m character in the energy).

Points: "sentinel" vertices (one per small rest-pose cluster on the hands, arms, legs and head, a few hundred)
plus whatever a stage adds. Each point is tested only against the segments it may reach: candidate triples are
chosen once on a pose, with slack for the motion an optimiser makes (:func:`candidate_triples`); the penetration
term is ``sum geodesic_weight * relu(depth - tolerance)^2`` with ``depth`` the blended-SDF depth beyond the bind
pose's.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS
from retarget_core.energy.pair_samples_kernel import segment_triples
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
    chosen = chosen[keep_cluster[parts.vertex_part[chosen]]]
    return chosen if parts.body is None else chosen[parts.body[chosen]]  # accessories are never sentinels


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
                      contact_weight: float = 1.0) -> TripleSet:  # fmt: skip
    """Triples for point vertices ``points (P,)`` posed ``(Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``
    at clip frames ``frames (Fa,)``: every allowed segment whose grid box, grown by ``slack``, holds the point
    and whose distance is below ``slack`` (m, or ``(P,)`` per point). ``exempt (F, S, 6)``: segment-of-point x cluster pairs in contact
    per clip frame (their tolerance is ``contact_tolerance``, their weight times ``contact_weight``: the hand is
    brought to the surface by the contact term, the sunk part only nudged out). ``only_penetrating``: keep
    depths > 0 only."""
    parts = sdf.parts
    part = parts.vertex_part.index_select(0, points)  # (P,)
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    lo = sdf.origin
    hi = lo + (sdf.size - 1).to(lo.dtype) * sdf.voxel[:, None]
    groups = []
    slack_p = torch.as_tensor(slack, dtype=torch.float64, device=posed.device).expand(posed.shape[1]).contiguous()
    posed64 = posed.detach().double().contiguous()
    with torch.no_grad():
        for j in range(parts.num_parts):
            ok_p = allowed[part, j]
            if sdf.grids[j] is None or not bool(ok_p.any()):
                continue
            f_i, pt = _segment_triples(sdf, j, posed64, seg_mats[:, j], torch.nonzero(ok_p).flatten(), slack_p,
                                       sdf.rest_depth[points, j], (lo[j], hi[j]), only_penetrating)  # fmt: skip
            if len(f_i) == 0:
                continue
            rest = sdf.rest_depth[points[pt], j]
            ex = exempt[frames[f_i], part[pt], cluster[j]]
            tol = torch.where(ex, torch.full_like(rest, contact_tolerance), torch.full_like(rest, -clearance))
            weight = sdf.geodesic_weight[points[pt], j] * torch.where(ex, contact_weight, 1.0)
            groups.append((j, f_i, pt, tol, weight, rest))
    return TripleSet(groups)


def _segment_triples(sdf: PartSDF, j: int, posed: Tensor, mats: Tensor, p_idx: Tensor, slack: Tensor, rest: Tensor,
                     box: tuple[Tensor, Tensor], only_penetrating: bool) -> tuple[Tensor, Tensor]:  # fmt: skip
    """(frame, point) ``(N,)`` of :func:`candidate_triples` for segment ``j`` (transforms ``mats (Fa, 3, 4)``)
    and the points ``p_idx (n,)`` of ``posed (Fa, P, 3)`` (float64), with each point's ``slack (P,)`` and
    bind-pose depth ``rest (P,)``: compiled (:func:`retarget_core.energy.pair_samples_kernel.segment_triples`)
    where it can be."""
    grid = sdf.grids[j]
    assert grid is not None
    m = mats.detach().double()
    lo, hi = box[0].double(), box[1].double()
    if posed.device.type == "cpu" and min(grid.shape[1:]) >= 2:
        found = segment_triples(grid.detach().numpy(), sdf.origin[j].double().numpy(), float(sdf.voxel[j]),
                                float(sdf.blend), lo.numpy(), hi.numpy(), m[..., :3].contiguous().numpy(),
                                m[..., 3].contiguous().numpy(), posed.numpy(), p_idx.numpy(), slack.numpy(),
                                rest.double().numpy(), only_penetrating)  # fmt: skip
        return torch.from_numpy(found[0]), torch.from_numpy(found[1])
    local = torch.einsum("fji,fnj->fni", m[..., :3], posed[:, p_idx] - m[:, None, :, 3])
    out = (local - torch.maximum(torch.minimum(local, hi), lo)).norm(dim=-1)
    f_i, n_i = torch.nonzero(out <= slack[p_idx][None], as_tuple=True)
    d = segment_distance(sdf, j, local[f_i, n_i])
    pt = p_idx[n_i]
    keep = (-d - rest[pt].double() > 0.0) if only_penetrating else d < slack[pt]
    return f_i[keep], pt[keep]


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


__all__ = [
    "SENTINEL_CLUSTERS",
    "TripleSet",
    "candidate_triples",
    "gather_rows",
    "group_depth",
    "near_triples",
    "penetration_energy",
    "penetration_energy_rows",
    "sentinel_vertices",
    "to_segment",
    "triple_depths",
]
