"""Compiled (numba, CPU) searches of one segment's grid, without gradients, each one pass instead of a dozen tensor
operations per segment; computed in float64:

- :func:`pair_cull` and :func:`segment_samples`: the per-frame bounds, the candidate search and the sampling of :func:`retarget_core.energy.sdf.sample_pairs`
  (per frame and cluster of vertices, the cluster's sphere against the grid box, then against the segment
  channel at its centre, then the blended signed distance of each member vertex);
- :func:`segment_triples`: the candidate triples of :func:`retarget_core.geometry.triples.candidate_triples`
  (per frame and point, the point within the slack of the grid box, then its blended distance).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from retarget_core.energy.sdf_kernel import _axis, _trilinear


@numba.njit(cache=True, nogil=True, inline="always")
def _local(rot: np.ndarray, trans: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    """A posed point taken to a segment's rest frame: ``rot (3, 3)^T (p - trans (3,))``."""
    dx, dy, dz = x - trans[0], y - trans[1], z - trans[2]
    return (rot[0, 0] * dx + rot[1, 0] * dy + rot[2, 0] * dz, rot[0, 1] * dx + rot[1, 1] * dy + rot[2, 1] * dz,
            rot[0, 2] * dx + rot[1, 2] * dy + rot[2, 2] * dz)  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _grid_value(grid: np.ndarray, lo: np.ndarray, voxel: float, blend: float, x: float, y: float, z: float,
                segment_only: bool) -> float:  # fmt: skip
    """Blended signed distance at a rest-frame point (``segment_only``: the segment channel alone), as
    :func:`retarget_core.energy.sdf_kernel._sample`."""
    i, tx, _, ox = _axis(x, lo[0], voxel, grid.shape[3])
    j, ty, _, oy = _axis(y, lo[1], voxel, grid.shape[2])
    k, tz, _, oz = _axis(z, lo[2], voxel, grid.shape[1])
    outside = math.sqrt(ox * ox + oy * oy + oz * oz)
    seg = _trilinear(grid, 0, i, j, k, tx, ty, tz)[0]
    if segment_only:
        return seg + outside
    char = _trilinear(grid, 1, i, j, k, tx, ty, tz)[0]
    p = min(max(seg / blend, 0.0), 1.0)
    return p * seg + (1.0 - p) * char + outside


@numba.njit(cache=True, nogil=True)
def _box_gap(lo: np.ndarray, hi: np.ndarray, x: float, y: float, z: float) -> float:
    """Distance of a point to the box ``lo, hi (3,)`` (0 inside)."""
    dx = x - min(max(x, lo[0]), hi[0])
    dy = y - min(max(y, lo[1]), hi[1])
    dz = z - min(max(z, lo[2]), hi[2])
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True, nogil=True)
def pair_cull(posed: np.ndarray, rows: np.ndarray, row_part: np.ndarray, row_cluster: np.ndarray, n_clusters: int,
              corners: np.ndarray, rot: np.ndarray, trans: np.ndarray, allowed: np.ndarray, has_grid: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The per-frame bounds of :func:`retarget_core.energy.sdf.sample_pairs`: ``overlap (F, S, S)``, where the
    box of part i's points (``rows (R,)`` of ``posed (F, N, 3)``, of parts ``row_part (R,)``) meets the posed
    box of segment j's grid (rest ``corners (S, 8, 3)``, transforms ``rot (F, S, 3, 3)``, ``trans (F, S, 3)``),
    for ``allowed (S, S)`` pairs with ``has_grid (S,)``; and ``centre (F, C, 3)``, the mean of each cluster's
    points (``row_cluster (R,)``)."""
    f_n, s_n = posed.shape[0], corners.shape[0]
    overlap = np.zeros((f_n, s_n, s_n), dtype=np.bool_)
    centre = np.zeros((f_n, n_clusters, 3))
    count = np.zeros(n_clusters)
    for r in range(len(rows)):
        count[row_cluster[r]] += 1.0
    p_lo, p_hi = np.empty((s_n, 3)), np.empty((s_n, 3))
    g_lo, g_hi = np.empty((s_n, 3)), np.empty((s_n, 3))
    for f in range(f_n):
        p_lo[:], p_hi[:] = np.inf, -np.inf
        for r in range(len(rows)):
            i, c = row_part[r], row_cluster[r]
            for a in range(3):
                x = posed[f, rows[r], a]
                p_lo[i, a], p_hi[i, a] = min(p_lo[i, a], x), max(p_hi[i, a], x)
                centre[f, c, a] += x
        for c in range(n_clusters):
            for a in range(3):
                centre[f, c, a] /= max(count[c], 1.0)
        for j in range(s_n):
            g_lo[j], g_hi[j] = np.inf, -np.inf
            for k in range(8):
                for a in range(3):
                    x = (rot[f, j, a, 0] * corners[j, k, 0] + rot[f, j, a, 1] * corners[j, k, 1]
                         + rot[f, j, a, 2] * corners[j, k, 2] + trans[f, j, a])  # fmt: skip
                    g_lo[j, a], g_hi[j, a] = min(g_lo[j, a], x), max(g_hi[j, a], x)
        for i in range(s_n):
            for j in range(s_n):
                if allowed[i, j] and has_grid[j]:
                    overlap[f, i, j] = (p_lo[i, 0] <= g_hi[j, 0] and p_lo[i, 1] <= g_hi[j, 1] and p_lo[i, 2] <= g_hi[j, 2]
                                        and p_hi[i, 0] >= g_lo[j, 0] and p_hi[i, 1] >= g_lo[j, 1]
                                        and p_hi[i, 2] >= g_lo[j, 2])  # fmt: skip
    return overlap, centre


@numba.njit(cache=True, nogil=True)
def segment_samples(grid: np.ndarray, lo: np.ndarray, voxel: float, blend: float, box_lo: np.ndarray,
                    box_hi: np.ndarray, rot: np.ndarray, trans: np.ndarray, posed: np.ndarray, cand: np.ndarray,
                    centre: np.ndarray, radius: np.ndarray, members: np.ndarray, slot: np.ndarray, reach: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The samples of one segment: per frame ``f`` and cluster ``c`` with ``cand[f, c]`` (frames, then clusters
    in order), when the cluster's sphere (``centre (F, C, 3)``, ``radius (C,)``) meets the grid box ``box_lo,
    box_hi (3,)`` in the segment's frame (``rot (F, 3, 3)``, ``trans (F, 3)``) and the segment channel at its
    centre minus its radius is within ``reach``: each member of ``members (C, K)`` (-1 padded; row of ``posed
    (F, N, 3)`` through ``slot (V,)`` when not empty). Returns frame, vertex ``(M,)`` and distance ``(M,)``."""
    cap = 1024
    frame = np.empty(cap, dtype=np.int64)
    vertex = np.empty(cap, dtype=np.int64)
    dist = np.empty(cap)
    n = 0
    for f in range(cand.shape[0]):
        for c in range(cand.shape[1]):
            if not cand[f, c]:
                continue
            cx, cy, cz = _local(rot[f], trans[f], centre[f, c, 0], centre[f, c, 1], centre[f, c, 2])
            if _box_gap(box_lo, box_hi, cx, cy, cz) > radius[c]:
                continue
            if _grid_value(grid, lo, voxel, blend, cx, cy, cz, True) - radius[c] > reach:
                continue
            for m in range(members.shape[1]):
                v = members[c, m]
                if v < 0:
                    break
                row = v if len(slot) == 0 else slot[v]
                x, y, z = _local(rot[f], trans[f], posed[f, row, 0], posed[f, row, 1], posed[f, row, 2])
                if n == cap:
                    cap *= 2
                    frame, vertex, dist = _grown(frame, cap), _grown(vertex, cap), _grown(dist, cap)
                frame[n], vertex[n] = f, v
                dist[n] = _grid_value(grid, lo, voxel, blend, x, y, z, False)
                n += 1
    return frame[:n], vertex[:n], dist[:n]


@numba.njit(cache=True, nogil=True)
def _grown(a: np.ndarray, cap: int) -> np.ndarray:
    """``a`` copied into an array of ``cap`` entries."""
    out = np.empty(cap, dtype=a.dtype)
    out[: len(a)] = a
    return out


@numba.njit(cache=True, nogil=True)
def segment_triples(grid: np.ndarray, lo: np.ndarray, voxel: float, blend: float, box_lo: np.ndarray,
                    box_hi: np.ndarray, rot: np.ndarray, trans: np.ndarray, posed: np.ndarray, points: np.ndarray,
                    slack: np.ndarray, rest: np.ndarray, only_penetrating: bool) -> tuple[np.ndarray, np.ndarray]:
    """(frame, point) ``(N,)`` each (frames, then points in order) of the points ``points (n,)`` (indices into
    ``posed (F, P, 3)``) within ``slack[point]`` of the grid box ``box_lo, box_hi (3,)`` in the segment's frame
    (``rot (F, 3, 3)``, ``trans (F, 3)``) whose blended distance is below ``slack[point]`` (``only_penetrating``:
    whose depth beyond ``rest[point]`` is positive)."""
    cap = 1024
    frame = np.empty(cap, dtype=np.int64)
    point = np.empty(cap, dtype=np.int64)
    n = 0
    for f in range(posed.shape[0]):
        for q in points:
            x, y, z = _local(rot[f], trans[f], posed[f, q, 0], posed[f, q, 1], posed[f, q, 2])
            if _box_gap(box_lo, box_hi, x, y, z) > slack[q]:
                continue
            d = _grid_value(grid, lo, voxel, blend, x, y, z, False)
            if not (-d - rest[q] > 0.0 if only_penetrating else d < slack[q]):
                continue
            if n == cap:
                cap *= 2
                frame, point = _grown(frame, cap), _grown(point, cap)
            frame[n], point[n] = f, q
            n += 1
    return frame[:n], point[:n]


__all__ = ["pair_cull", "segment_samples", "segment_triples"]
