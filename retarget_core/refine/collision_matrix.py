"""Paper 2's collision detection (section 4.3): the segment distance matrix ``M_dist`` with the masking matrix
Omega, reduced to the 6 x 6 cluster collision matrix ``M_col``.

Omega (section 7.1) ignores a segment with itself, neighbouring segments on the skeleton, segments of the same
cluster and upper arm against chest (:meth:`BodyParts.collision_mask` with ``ignore_arm_chest``). Row ``c_i``
of ``M_col`` holds the deepest penetration of a vertex of cluster ``c_i`` into a segment of cluster ``c_j``
(m, >= 0, diagonal 0; not symmetric, as in the paper: vertices of i in the SDF of j).

Choice: paper 2 measures raw depths. Bodies whose thighs or arms touch at rest then always show a collision,
so ``beyond_rest=True`` subtracts the bind-pose depth of each vertex (as the resolver's energy does).
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, BodyParts
from retarget_core.energy.sdf import PairSamples, PartSDF, _pair_values, distance_matrix, sample_pairs


def paper2_mask(parts: BodyParts) -> Tensor:
    """Omega as a ``(S, S)`` bool of tested pairs: not the same segment, not neighbours, not the same cluster,
    not upper arm against chest."""
    return parts.collision_mask(ignore_arm_chest=True)


def segment_distance_matrix(sdf: PartSDF, posed: Tensor, seg_mats: Tensor) -> Tensor:
    """``M_dist + Omega`` ``(F, S, S)``: smallest signed distance of segment i's vertices to segment j (m,
    capped at the grid margin), ``+inf`` where Omega masks the pair. ``posed (F, V, 3)``, ``seg_mats (F, S, 3, 4)``."""
    mask = paper2_mask(sdf.parts)
    samples = sample_pairs(sdf, posed, seg_mats, mask)
    dist = distance_matrix(sdf, samples, posed.shape[0])
    return torch.where(mask[None], dist, torch.full_like(dist, float("inf")))


def cluster_matrix_from_samples(sdf: PartSDF, samples: PairSamples, frames: int, beyond_rest: bool = False) -> Tensor:
    """``M_col (F, 6, 6)`` from pair samples (already restricted to Omega's pairs): per (cluster of the
    vertex, cluster of the segment) the largest penetration depth (m)."""
    parts = sdf.parts
    c_n = len(CLUSTERS)
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    depth = -samples.distance
    if beyond_rest:
        depth = depth - _pair_values(sdf.rest_depth, samples).to(depth.dtype)
    depth = depth.clamp_min(0.0)
    ci = cluster.index_select(0, parts.vertex_part.index_select(0, samples.vertex))
    cj = cluster.index_select(0, samples.part)
    key = (samples.frame * c_n + ci) * c_n + cj
    out = depth.new_zeros(frames * c_n * c_n).scatter_reduce(0, key, depth, "amax", include_self=True)
    out = out.view(frames, c_n, c_n)
    return out * (1.0 - torch.eye(c_n, dtype=out.dtype))[None]


def cluster_collision_matrix(sdf: PartSDF, posed: Tensor, seg_mats: Tensor, beyond_rest: bool = False) -> Tensor:
    """Paper 2's ``M_col (F, 6, 6)`` (eqs. 5-7) for posed vertices ``(F, V, 3)`` and segment transforms
    ``(F, S, 3, 4)``; clusters in :data:`CLUSTERS` order. Equal to ``max(-min(M_dist[I_ci, I_cj]), 0)``
    (up to the grid margin, beyond which nothing penetrates); differentiable in the posed inputs."""
    samples = sample_pairs(sdf, posed, seg_mats, paper2_mask(sdf.parts))
    return cluster_matrix_from_samples(sdf, samples, posed.shape[0], beyond_rest)


__all__ = [
    "cluster_collision_matrix",
    "cluster_matrix_from_samples",
    "paper2_mask",
    "segment_distance_matrix",
]
