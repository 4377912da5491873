"""Triangle-triangle intersection between two vertex groups of one posed mesh: an axis-aligned bounding box
broad phase and a vectorised narrow phase (numpy; detection is not differentiated)."""

from __future__ import annotations

import numpy as np

EPS = 1e-12


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack(
        [a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2], a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]],
        axis=1,
    )


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def segments_hit_triangles(p0: np.ndarray, p1: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: segment ``p0 -> p1`` crosses triangle ``(a, b, c)``; every input ``(N, 3)``
    (Moller-Trumbore with the ray parameter limited to the segment)."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = _cross(d, e2)
    det = _dot(e1, h)
    ok = np.abs(det) > EPS
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p0 - a
    u = _dot(s, h) * inv
    q = _cross(s, e1)
    v = _dot(d, q) * inv
    t = _dot(e2, q) * inv
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def triangles_intersect(ta: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: triangles ``ta (N, 3, 3)`` and ``tb (N, 3, 3)`` intersect (an edge of one crosses the
    other). Exactly coplanar overlaps, which have no volume, are not reported."""
    hit = np.zeros(ta.shape[0], dtype=bool)
    for k in range(3):
        k1 = (k + 1) % 3
        hit |= segments_hit_triangles(ta[:, k], ta[:, k1], tb[:, 0], tb[:, 1], tb[:, 2])
        hit |= segments_hit_triangles(tb[:, k], tb[:, k1], ta[:, 0], ta[:, 1], ta[:, 2])
    return hit


def triangle_boxes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners ``(T, 3)`` of the boxes of triangles ``faces (T, 3)`` of ``vertices (V, 3)``."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def _cells(lo: np.ndarray, hi: np.ndarray, origin: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(triangle, cell key) for every grid cell each box ``lo..hi (T, 3)`` touches."""
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    c1 = np.floor((hi - origin) / cell).astype(np.int64)
    n = c1 - c0 + 1  # (T, 3)
    count = n.prod(1)
    tri = np.repeat(np.arange(len(lo)), count)
    local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    nx, ny = n[tri, 0], n[tri, 1]
    ix = c0[tri, 0] + local % nx
    iy = c0[tri, 1] + (local // nx) % ny
    iz = c0[tri, 2] + local // (nx * ny)
    return tri, (ix * 1_048_576 + iy) * 1_048_576 + iz


def candidate_pairs(a_lo: np.ndarray, a_hi: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of boxes (indices into a and b) that overlap, found through a uniform grid of cells about the size
    of the boxes (sort and search, no Python loop)."""
    extent = np.concatenate([a_hi - a_lo, b_hi - b_lo])
    cell = max(float(np.median(extent.max(1))) * 1.5, 1e-6)
    origin = np.minimum(a_lo.min(0), b_lo.min(0))
    ta, ka = _cells(a_lo, a_hi, origin, cell)
    tb, kb = _cells(b_lo, b_hi, origin, cell)
    order = np.argsort(kb, kind="stable")
    tb, kb = tb[order], kb[order]
    start = np.searchsorted(kb, ka, side="left")
    stop = np.searchsorted(kb, ka, side="right")
    count = stop - start
    ia = np.repeat(ta, count)
    offs = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    ib = tb[np.repeat(start, count) + offs]
    if len(ia) == 0:
        return ia, ib
    key = np.unique(ia * (len(b_lo) + 1) + ib)
    ia, ib = key // (len(b_lo) + 1), key % (len(b_lo) + 1)
    keep = ((a_lo[ia] <= b_hi[ib]) & (a_hi[ia] >= b_lo[ib])).all(-1)
    return ia[keep], ib[keep]


def intersecting_pairs(
    vertices: np.ndarray, faces_a: np.ndarray, faces_b: np.ndarray, first_only: bool = False, block: int = 200_000
) -> np.ndarray:
    """Index pairs ``(K, 2)`` into ``faces_a (Ta, 3)`` and ``faces_b (Tb, 3)`` of intersecting triangles of the
    posed ``vertices (V, 3)``: overlapping triangle boxes through a uniform grid (broad phase), then the exact
    test on those pairs in blocks of ``block``. ``first_only``: stop after the first block with a hit."""
    if len(faces_a) == 0 or len(faces_b) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    a_lo, a_hi = triangle_boxes(vertices, faces_a)
    b_lo, b_hi = triangle_boxes(vertices, faces_b)
    ia = np.nonzero(((a_lo <= b_hi.max(0)) & (a_hi >= b_lo.min(0))).all(-1))[0]
    ib = np.nonzero(((b_lo <= a_hi.max(0)) & (b_hi >= a_lo.min(0))).all(-1))[0]
    if len(ia) == 0 or len(ib) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pa, pb = candidate_pairs(a_lo[ia], a_hi[ia], b_lo[ib], b_hi[ib])
    fa, fb = ia[pa], ib[pb]
    out = []
    for s in range(0, len(fa), block):
        ca, cb = fa[s : s + block], fb[s : s + block]
        hit = triangles_intersect(vertices[faces_a[ca]], vertices[faces_b[cb]])
        if hit.any():
            out.append(np.stack([ca[hit], cb[hit]], axis=1))
            if first_only:
                break
    return np.concatenate(out) if out else np.zeros((0, 2), dtype=np.int64)
