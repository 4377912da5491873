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


def intersecting_pairs(vertices: np.ndarray, faces_a: np.ndarray, faces_b: np.ndarray, max_pairs: int = 2_000_000) -> np.ndarray:
    """Index pairs ``(K, 2)`` into ``faces_a (Ta, 3)`` and ``faces_b (Tb, 3)`` of intersecting triangles of the
    posed ``vertices (V, 3)``. Triangles outside the other group's box are dropped first, then box pairs are
    tested in blocks of at most ``max_pairs``, then the exact test runs on overlapping boxes only."""
    if len(faces_a) == 0 or len(faces_b) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    a_lo, a_hi = triangle_boxes(vertices, faces_a)
    b_lo, b_hi = triangle_boxes(vertices, faces_b)
    ia = np.nonzero(((a_lo <= b_hi.max(0)) & (a_hi >= b_lo.min(0))).all(-1))[0]
    ib = np.nonzero(((b_lo <= a_hi.max(0)) & (b_hi >= a_lo.min(0))).all(-1))[0]
    if len(ia) == 0 or len(ib) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    out = []
    rows = max(1, max_pairs // len(ib))
    for s in range(0, len(ia), rows):
        sa = ia[s : s + rows]
        over = ((a_lo[sa, None] <= b_hi[None, ib]) & (a_hi[sa, None] >= b_lo[None, ib])).all(-1)
        pa, pb = np.nonzero(over)
        if len(pa) == 0:
            continue
        fa, fb = sa[pa], ib[pb]
        hit = triangles_intersect(vertices[faces_a[fa]], vertices[faces_b[fb]])
        if hit.any():
            out.append(np.stack([fa[hit], fb[hit]], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2), dtype=np.int64)
