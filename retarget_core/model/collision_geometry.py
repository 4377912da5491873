"""Paper 2's collision detection for the learned resolver, on a fixed set of limb points (batched, differentiable).

The learned model reads (and is trained against) the cluster collision matrix ``M_col`` of the four limb rows
(paper 2, eqs. 5-7), computed here on "limb points": one vertex per small rest-pose cell of the arm and leg
segments (:func:`~retarget_core.refine.collision_energy.sentinel_vertices`, a 3 cm cell at 1.80 m: about 1,400
of 13k vertices). Only limb rows matter to the four per-limb models (row c holds the vertices of cluster c inside
the other clusters), so no torso or head vertex is posed.

Choices where paper 2 leaves room (or where our judge differs), written down here:
- pairs: ``sdf.allowed`` (a segment with itself, neighbours and same-cluster pairs masked: paper 2's Omega)
  restricted to the pairs the acceptance judge tests (:data:`~retarget_core.refine.collision_check.JUDGED_TESTS`:
  an arm against torso, head, the other arm and the legs; a leg against the other leg and the arms). Paper 2 also
  masks upper arm against chest; we keep it (the upper arm in a bulky chest is the commonest collision the judge
  counts) and instead weight each depth by the geodesic ramp of :mod:`retarget_core.energy.sdf`, which leaves the
  joint folds (armpit, crotch) out as the judge does;
- depths are measured beyond the bind pose's (bodies whose thighs touch at rest do not always collide);
- random segment padding (paper 2, eq. 14) pads the signed distance of a (point segment i, segment j) pair by
  ``-(p_i + p_j)`` before the depth is taken;
- a pair of (hand's arm, touched cluster) that is a hand contact on the source is not a collision (both ways):
  a contact is a target the optimisation stage keeps, not something the model pushes apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, BodyParts
from retarget_core.character import Character
from retarget_core.energy.sdf import PartSDF
from retarget_core.geometry.judged_pairs import judged_cluster_table
from retarget_core.geometry.point_poser import PointPoser
from retarget_core.geometry.triples import TripleSet, candidate_triples, sentinel_vertices, triple_depths

LIMBS: tuple[str, ...] = ("left_arm", "right_arm", "left_leg", "right_leg")
"""The four segment clusters that get a model (paper 2, section 5), in :data:`CLUSTERS` names."""
LIMB_ROWS: tuple[int, ...] = tuple(CLUSTERS.index(c) for c in LIMBS)
POINT_CELL_M = 0.03  # limb points: one per 3 cm rest-pose cell (at 1.80 m)
SLACK_M = 0.05  # a point is tested against a segment when within this of it on the given pose (at 1.80 m)


@dataclass
class LimbPoints:
    """The limb points of one body and what poses them.

    points: ``(P,)`` vertex indices; segment: ``(P,)`` their segment; poser: poses them and returns the segment
    transforms; pair_ok: ``(S, S)`` bool, (point segment, segment) pairs measured; scale: body -> 1.80 m."""

    points: Tensor
    segment: Tensor
    poser: PointPoser
    pair_ok: Tensor
    scale: float


def limb_points(character: Character, parts: BodyParts, sdf: PartSDF, cell_m: float = POINT_CELL_M) -> LimbPoints:
    """The :class:`LimbPoints` of a body (its parts and SDFs from the body cache)."""
    scale = sdf.scale_to_180
    limb_segs = [s for s in range(parts.num_parts) if CLUSTERS[parts.cluster[s]] in LIMBS]
    pts = sentinel_vertices(sdf, character.vertices.float(), cell_m / scale, limb_segs)
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    table = judged_cluster_table()
    pair_ok = sdf.allowed & table[cluster[:, None], cluster[None, :]]
    return LimbPoints(pts, parts.vertex_part.index_select(0, pts), PointPoser(character, pts, parts.joints), pair_ok, scale)


def find_triples(sdf: PartSDF, lp: LimbPoints, posed: Tensor, seg_mats: Tensor, slack_m: float = SLACK_M) -> TripleSet:
    """Candidate (frame, point, segment) triples ``posed (B, P, 3)`` may reach: every measured pair within
    ``slack_m`` (at 1.80 m) of the segment on the given pose (no gradients)."""
    b_n = posed.shape[0]
    exempt = torch.zeros(b_n, sdf.parts.num_parts, len(CLUSTERS), dtype=torch.bool)
    with torch.no_grad():
        return candidate_triples(sdf, lp.points, posed, seg_mats, torch.arange(b_n), exempt, lp.pair_ok,
                                 slack_m / lp.scale, 0.0, 0.0)  # fmt: skip


def cluster_depths(sdf: PartSDF, lp: LimbPoints, triples: TripleSet, posed: Tensor, seg_mats: Tensor,
                   pad: Tensor | None = None, exempt: Tensor | None = None) -> Tensor:  # fmt: skip
    """``M_col (B, 6, 6)``: per (cluster of the point, cluster of the segment) the deepest geodesically weighted
    penetration beyond the bind pose (m at the body's scale, >= 0), differentiable in ``posed (B, P, 3)`` and
    ``seg_mats (B, S, 3, 4)``. ``pad (B, S)``: random segment padding (m, positive thickens); ``exempt (B, 6, 6)``
    bool: cluster pairs that are not collisions (contacts)."""
    b_n = posed.shape[0]
    c_n = len(CLUSTERS)
    cluster = torch.tensor(sdf.parts.cluster, dtype=torch.long)
    keys, vals = [], []
    for (j, f_i, pt, _tol, weight, _rest), depth in zip(triples.groups, triple_depths(sdf, triples, posed, seg_mats), strict=True):
        seg_i = lp.segment.index_select(0, pt)
        if pad is not None:
            depth = depth + pad[f_i, seg_i] + pad[f_i, j]
        vals.append(depth.clamp_min(0.0) * weight)
        keys.append((f_i * c_n + cluster[seg_i]) * c_n + cluster[j])
    out = posed.new_zeros(b_n * c_n * c_n)
    if keys:
        out = out.scatter_reduce(0, torch.cat(keys), torch.cat(vals), "amax", include_self=True)
    out = out.view(b_n, c_n, c_n)
    if exempt is not None:
        out = out.masked_fill(exempt, 0.0)
    return out


def contact_exempt(frames: int, frame: Tensor, hand_cluster: Tensor, touched_cluster: Tensor) -> Tensor:
    """``(F, 6, 6)`` bool: on each contact's frame (those below ``frames``), (hand's cluster, touched cluster) and
    the reverse pair."""
    out = torch.zeros(frames, len(CLUSTERS), len(CLUSTERS), dtype=torch.bool)
    keep = frame < frames
    frame, hand_cluster, touched_cluster = frame[keep], hand_cluster[keep], touched_cluster[keep]
    if frame.numel():
        out[frame, hand_cluster, touched_cluster] = True
        out[frame, touched_cluster, hand_cluster] = True
    return out


def collision_matrix(sdf: PartSDF, lp: LimbPoints, local_rot: Tensor, trans: Tensor, exempt: Tensor | None = None,
                     chunk: int = 256) -> Tensor:  # fmt: skip
    """``M_col (F, 6, 6)`` of a whole motion (no gradients), in chunks of ``chunk`` frames; ``local_rot (F, J, 3,
    3)``, ``trans (F, J, 3)``, ``exempt (F, 6, 6)`` as :func:`cluster_depths`."""
    out = []
    with torch.no_grad():
        for s in range(0, local_rot.shape[0], chunk):
            posed, mats, _ = lp.poser(local_rot[s : s + chunk], trans[s : s + chunk])
            tri = find_triples(sdf, lp, posed, mats, slack_m=0.0)
            ex = exempt[s : s + chunk] if exempt is not None else None
            out.append(cluster_depths(sdf, lp, tri, posed, mats, exempt=ex))
    return torch.cat(out) if out else local_rot.new_zeros(0, len(CLUSTERS), len(CLUSTERS))


__all__ = [
    "LIMBS",
    "LIMB_ROWS",
    "LimbPoints",
    "cluster_depths",
    "collision_matrix",
    "contact_exempt",
    "find_triples",
    "limb_points",
]
