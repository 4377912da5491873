"""Compiled CPU walks of the triangle tree (:mod:`retarget_core.geometry.triangle_bvh`): each query walks the
tree depth first on its own, nearest box first, pruned by the best distance so far, instead of the level-wide
frontier of (query, node) pairs the tensor walk keeps. Same answers (the tensor walk is the reference the tests
compare with); on the CPU several times faster, since a query visits a few dozen boxes and no frontier is
gathered, sorted or copied.

The boxes are read in heap order (:attr:`PosedBoxes.lo_heap`): node ``i`` of level ``l`` at ``2 ** l - 1 + i``,
its children at ``2 h + 1`` and ``2 h + 2``. Compiled with numba (cached on disk after the first call); the
functions release the GIL, so blocks of queries run on threads (:func:`run_in_blocks`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar, cast

import numba
import numpy as np
import torch

MIN_BLOCK = 2048  # queries per thread at least: fewer are not worth a thread's start
MIN_ROWS = 1 << 18  # rows read per thread at least by the box kernels (a thread pool's start costs ~0.2 ms)

F = TypeVar("F", bound=Callable[..., Any])


def _compiled(fn: F) -> F:
    """``fn`` compiled by numba (cached on disk; it releases the GIL), typed as itself."""
    return cast(F, numba.njit(cache=True, nogil=True)(fn))


@_compiled
def _box_distance(lo: np.ndarray, hi: np.ndarray, px: float, py: float, pz: float) -> float:
    """Distance of point ``p`` to the box ``lo, hi (3,)`` (0 inside)."""
    dx = max(lo[0] - px, 0.0) + max(px - hi[0], 0.0)
    dy = max(lo[1] - py, 0.0) + max(py - hi[1], 0.0)
    dz = max(lo[2] - pz, 0.0) + max(pz - hi[2], 0.0)
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@_compiled
def _segment_point(px: float, py: float, pz: float, x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Closest point to ``p`` on the segment ``x, y (3,)``."""
    dx, dy, dz = y[0] - x[0], y[1] - x[1], y[2] - x[2]
    t = ((px - x[0]) * dx + (py - x[1]) * dy + (pz - x[2]) * dz) / max(dx * dx + dy * dy + dz * dz, 1e-300)
    t = min(max(t, 0.0), 1.0)
    return x[0] + dx * t, x[1] + dy * t, x[2] + dz * t


@_compiled
def _edge_point(px: float, py: float, pz: float, a: np.ndarray, b: np.ndarray, c: np.ndarray
                ) -> tuple[float, float, float]:  # fmt: skip
    """Closest point to ``p`` on the edges of a triangle without area (the first of the nearest)."""
    best, bx, by, bz = np.inf, 0.0, 0.0, 0.0
    for x, y in ((a, b), (b, c), (a, c)):
        qx, qy, qz = _segment_point(px, py, pz, x, y)
        d = (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2
        if d < best:
            best, bx, by, bz = d, qx, qy, qz
    return bx, by, bz


@_compiled
def closest_point(px: float, py: float, pz: float, a: np.ndarray, b: np.ndarray, c: np.ndarray
                  ) -> tuple[float, float, float]:  # fmt: skip
    """Closest point to ``p`` on triangle ``a, b, c (3,)`` (Ericson 5.1.5, as
    :func:`retarget_core.geometry.closest_point.closest_points`; without area: its edges)."""
    abx, aby, abz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    acx, acy, acz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    apx, apy, apz = px - a[0], py - a[1], pz - a[2]
    d1, d2 = abx * apx + aby * apy + abz * apz, acx * apx + acy * apy + acz * apz
    bpx, bpy, bpz = px - b[0], py - b[1], pz - b[2]
    d3, d4 = abx * bpx + aby * bpy + abz * bpz, acx * bpx + acy * bpy + acz * bpz
    cpx, cpy, cpz = px - c[0], py - c[1], pz - c[2]
    d5, d6 = abx * cpx + aby * cpy + abz * cpz, acx * cpx + acy * cpy + acz * cpz
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    ab_len = math.sqrt(abx * abx + aby * aby + abz * abz)
    ac_len = math.sqrt(acx * acx + acy * acy + acz * acz)
    if abs(denom) <= 1e-30 * max(ab_len * ac_len, 1e-300) + 1e-300:  # no area: the nearest of its edges
        return _edge_point(px, py, pz, a, b, c)
    if d1 <= 0 and d2 <= 0:
        return a[0], a[1], a[2]
    if d3 >= 0 and d4 <= d3:
        return b[0], b[1], b[2]
    if d6 >= 0 and d5 <= d6:
        return c[0], c[1], c[2]
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        t = min(max(d1 / (d1 - d3) if d1 - d3 != 0 else d1, 0.0), 1.0)
        return a[0] + abx * t, a[1] + aby * t, a[2] + abz * t
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        t = min(max(d2 / (d2 - d6) if d2 - d6 != 0 else d2, 0.0), 1.0)
        return a[0] + acx * t, a[1] + acy * t, a[2] + acz * t
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        den = (d4 - d3) + (d5 - d6)
        t = min(max((d4 - d3) / den if den != 0 else d4 - d3, 0.0), 1.0)
        return b[0] + (c[0] - b[0]) * t, b[1] + (c[1] - b[1]) * t, b[2] + (c[2] - b[2]) * t
    v, w = vb / denom, vc / denom
    return a[0] + abx * v + acx * w, a[1] + aby * v + acy * w, a[2] + abz * v + acz * w


@_compiled
def triangle_distance(px: float, py: float, pz: float, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Exact distance of ``p`` to triangle ``a, b, c (3,)`` (:func:`closest_point`)."""
    qx, qy, qz = closest_point(px, py, pz, a, b, c)
    ex, ey, ez = px - qx, py - qy, pz - qz
    return math.sqrt(ex * ex + ey * ey + ez * ez)


@_compiled
def closest_walk(lo: np.ndarray, hi: np.ndarray, vertices: np.ndarray, faces: np.ndarray, leaf_faces: np.ndarray,
                 depth: int, rows: np.ndarray, points: np.ndarray, limit: np.ndarray, tie: float,
                 out_distance: np.ndarray, out_face: np.ndarray) -> None:  # fmt: skip
    """Per query ``q``: the exact distance from ``points[q] (3,)`` to the triangles of stored frame ``rows[q]``
    within ``limit[q]`` and the closest triangle (of those within ``tie`` of it, the lowest index), into
    ``out_distance, out_face (Q,)`` (inf and -1: none within). ``lo, hi (S, H, 3)`` heap-ordered boxes,
    ``vertices (S, V, 3)``, ``faces (T, 3)``, ``leaf_faces (L, K)`` (-1 padding at the end)."""
    first_leaf = (1 << depth) - 1
    node_stack = np.empty(depth + 2, dtype=np.int64)
    near_stack = np.empty(depth + 2, dtype=vertices.dtype)
    for q in range(len(points)):
        s = rows[q]
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        best, best_face = limit[q], -1
        top = 0
        node_stack[0] = 0
        near_stack[0] = _box_distance(lo[s, 0], hi[s, 0], px, py, pz)
        while top >= 0:
            node, near = node_stack[top], near_stack[top]
            top -= 1
            if near > best + tie:
                continue
            if node >= first_leaf:
                for k in range(leaf_faces.shape[1]):
                    f = leaf_faces[node - first_leaf, k]
                    if f < 0:
                        break
                    tri = faces[f]
                    d = triangle_distance(px, py, pz, vertices[s, tri[0]], vertices[s, tri[1]], vertices[s, tri[2]])
                    if d < best - tie or (d <= best and best_face < 0):
                        best, best_face = d, f
                    elif d <= best + tie:
                        best, best_face = min(best, d), min(best_face, f)
                continue
            left, right = 2 * node + 1, 2 * node + 2
            n_left = _box_distance(lo[s, left], hi[s, left], px, py, pz)
            n_right = _box_distance(lo[s, right], hi[s, right], px, py, pz)
            if n_left <= n_right:  # the nearer child on top: walked first
                left, right, n_left, n_right = right, left, n_right, n_left
            top += 1
            node_stack[top], near_stack[top] = left, n_left
            top += 1
            node_stack[top], near_stack[top] = right, n_right
        out_distance[q] = best if best_face >= 0 else np.inf
        out_face[q] = best_face


@_compiled
def _ray_sign(ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, a: np.ndarray, b: np.ndarray,
              c: np.ndarray) -> float:  # fmt: skip
    """+1 / -1 where the ray from ``o`` along ``d`` crosses triangle ``a, b, c`` (by its orientation), 0 where it
    misses (Moller-Trumbore, as the tensor walk's ``_ray_crossings``)."""
    e1x, e1y, e1z = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    e2x, e2y, e2z = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    pvx, pvy, pvz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * pvx + e1y * pvy + e1z * pvz
    if abs(det) <= 1e-300:
        return 0.0
    inv = 1.0 / det
    tx, ty, tz = ox - a[0], oy - a[1], oz - a[2]
    u = (tx * pvx + ty * pvy + tz * pvz) * inv
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if u >= 0 and v >= 0 and u + v <= 1 and t > 0:
        return 1.0 if det > 0 else -1.0
    return 0.0


@_compiled
def _ray_meets_box(lo: np.ndarray, hi: np.ndarray, ox: float, oy: float, oz: float, ix: float, iy: float,
                   iz: float) -> bool:  # fmt: skip
    """The ray from ``o`` (``i``: one over its direction) meets the box ``lo, hi (3,)``."""
    t1, t2 = (lo[0] - ox) * ix, (hi[0] - ox) * ix
    t_in, t_out = min(t1, t2), max(t1, t2)
    t1, t2 = (lo[1] - oy) * iy, (hi[1] - oy) * iy
    t_in, t_out = max(t_in, min(t1, t2)), min(t_out, max(t1, t2))
    t1, t2 = (lo[2] - oz) * iz, (hi[2] - oz) * iz
    t_in, t_out = max(t_in, min(t1, t2)), min(t_out, max(t1, t2))
    return t_out >= max(t_in, 0.0)


@_compiled
def winding_walk(lo: np.ndarray, hi: np.ndarray, vertices: np.ndarray, faces: np.ndarray, leaf_faces: np.ndarray,
                 depth: int, rows: np.ndarray, points: np.ndarray, direction: np.ndarray,
                 out: np.ndarray) -> None:  # fmt: skip
    """Per query ``q``: the signed count of triangles of stored frame ``rows[q]`` the ray from ``points[q]``
    along ``direction (3,)`` crosses, into ``out (Q,)``; arrays as :func:`closest_walk`."""
    first_leaf = (1 << depth) - 1
    dx, dy, dz = direction[0], direction[1], direction[2]
    ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / dz
    stack = np.empty(depth + 2, dtype=np.int64)
    for q in range(len(points)):
        s = rows[q]
        ox, oy, oz = points[q, 0], points[q, 1], points[q, 2]
        total = 0.0
        top = 0
        stack[0] = 0
        while top >= 0:
            node = stack[top]
            top -= 1
            if not _ray_meets_box(lo[s, node], hi[s, node], ox, oy, oz, ix, iy, iz):
                continue
            if node >= first_leaf:
                for k in range(leaf_faces.shape[1]):
                    f = leaf_faces[node - first_leaf, k]
                    if f < 0:
                        break
                    tri = faces[f]
                    total += _ray_sign(ox, oy, oz, dx, dy, dz, vertices[s, tri[0]], vertices[s, tri[1]],
                                       vertices[s, tri[2]])  # fmt: skip
                continue
            top += 1
            stack[top] = 2 * node + 1
            top += 1
            stack[top] = 2 * node + 2
        out[q] = total


@_compiled
def refit_boxes(vertices: np.ndarray, faces: np.ndarray, leaf_faces: np.ndarray, depth: int, lo: np.ndarray,
                hi: np.ndarray) -> None:  # fmt: skip
    """Every node's box on each posed frame ``vertices (S, V, 3)`` into the heap-ordered ``lo, hi (S, H, 3)``:
    a leaf's from its triangles' corners (an empty leaf: +inf and -inf), a parent's from its children's."""
    first_leaf = (1 << depth) - 1
    for s in range(vertices.shape[0]):
        for leaf in range(leaf_faces.shape[0]):  # the corners' bounds kept in locals: the loop does not store them
            lx, ly, lz, hx, hy, hz = np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf
            for k in range(leaf_faces.shape[1]):
                f = leaf_faces[leaf, k]
                if f < 0:
                    break
                for c in range(3):
                    i = faces[f, c]
                    x, y, z = vertices[s, i, 0], vertices[s, i, 1], vertices[s, i, 2]
                    lx, ly, lz, hx, hy, hz = min(lx, x), min(ly, y), min(lz, z), max(hx, x), max(hy, y), max(hz, z)
            node = first_leaf + leaf
            lo[s, node, 0], lo[s, node, 1], lo[s, node, 2] = lx, ly, lz
            hi[s, node, 0], hi[s, node, 1], hi[s, node, 2] = hx, hy, hz
        for node in range(first_leaf - 1, -1, -1):
            a, b = 2 * node + 1, 2 * node + 2
            for x in range(3):
                lo[s, node, x] = min(lo[s, a, x], lo[s, b, x])
                hi[s, node, x] = max(hi[s, a, x], hi[s, b, x])


@_compiled
def indexed_bounds(posed: np.ndarray, index: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """The box of the rows ``index (N,)`` of each frame of ``posed (n, V, 3)`` into ``lo, hi (n, 3)``, without
    gathering them (a part's box per frame: a gather copied tens of MB per chunk on a large body)."""
    for f in range(posed.shape[0]):
        lx, ly, lz, hx, hy, hz = np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf
        for i in index:
            x, y, z = posed[f, i, 0], posed[f, i, 1], posed[f, i, 2]
            lx, ly, lz, hx, hy, hz = min(lx, x), min(ly, y), min(lz, z), max(hx, x), max(hy, y), max(hz, z)
        lo[f, 0], lo[f, 1], lo[f, 2], hi[f, 0], hi[f, 1], hi[f, 2] = lx, ly, lz, hx, hy, hz


@_compiled
def _in_box(posed: np.ndarray, f: int, i: int, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether row ``i`` of frame ``f`` of ``posed (n, V, 3)`` lies in that frame's box ``lo, hi (n, 3)``."""
    for x in range(3):
        v = posed[f, i, x]
        if not (lo[f, x] <= v and v <= hi[f, x]):
            return False
    return True


@_compiled
def count_in_boxes(posed: np.ndarray, index: np.ndarray, lo: np.ndarray, hi: np.ndarray, first: int, last: int,
                   count: np.ndarray) -> None:  # fmt: skip
    """Into ``count[f]``, for the frames ``first <= f < last``, how many rows ``index (K,)`` of frame ``f`` of
    ``posed (n, V, 3)`` lie in its box ``lo, hi (n, 3)`` (without gathering them)."""
    for f in range(first, last):
        c = 0
        for i in index:
            if _in_box(posed, f, i, lo, hi):
                c += 1
        count[f] = c


@_compiled
def fill_in_boxes(posed: np.ndarray, index: np.ndarray, lo: np.ndarray, hi: np.ndarray, first: int, last: int,
                  start: np.ndarray, frame: np.ndarray, which: np.ndarray) -> None:  # fmt: skip
    """:func:`count_in_boxes`'s rows written from ``start[f]`` on: their frame and their place in ``index``."""
    for f in range(first, last):
        n = start[f]
        for k in range(len(index)):
            if _in_box(posed, f, index[k], lo, hi):
                frame[n], which[n] = f, k
                n += 1


def rows_bounds(posed: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 3)`` low and high corners of the box of the rows ``index (K,)`` of each frame of ``posed (n, V, 3)``
    (float64, contiguous), without gathering them; inf and -inf where ``K`` is 0."""
    n = posed.shape[0]
    lo, hi = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    if len(index):
        index = np.ascontiguousarray(index, dtype=np.int64)
        run_in_blocks(lambda b: indexed_bounds(posed[b], index, lo[b], hi[b]), n, _frames_per_block(index))
    return lo, hi


def rows_in_boxes(posed: np.ndarray, index: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows ``index (K,)`` of each frame of ``posed (n, V, 3)`` (contiguous) inside that frame's box ``lo, hi
    (n, 3)``: frame and place in ``index``, ``(N,)`` each, by frame then place (as ``nonzero`` of the gathered
    test gives them)."""
    n = posed.shape[0]
    count = np.zeros(n, dtype=np.int64)
    block = _frames_per_block(index)
    run_in_blocks(lambda b: count_in_boxes(posed, index, lo, hi, *b.indices(n)[:2], count), n, block)
    start = np.concatenate([np.zeros(1, dtype=np.int64), np.cumsum(count)])
    frame, which = np.empty(int(start[-1]), dtype=np.int64), np.empty(int(start[-1]), dtype=np.int64)
    run_in_blocks(lambda b: fill_in_boxes(posed, index, lo, hi, *b.indices(n)[:2], start, frame, which), n, block)
    return frame, which


def _frames_per_block(index: np.ndarray) -> int:
    """Frames a thread of the box kernels takes at least, reading the rows ``index (K,)`` of each."""
    return max(1, MIN_ROWS // max(1, len(index)))


def run_in_blocks(walk: Callable[[slice], None], count: int, min_block: int = MIN_BLOCK) -> None:
    """``walk(block)`` over ``count`` items (queries, frames) in blocks, one per torch thread (the walks release
    the GIL); a block holds at least ``min_block`` items."""
    threads = max(1, min(torch.get_num_threads(), count // min_block))
    if threads == 1:
        walk(slice(0, count))
        return
    step = -(-count // threads)
    list(_pool(threads).map(walk, [slice(s, s + step) for s in range(0, count, step)]))


_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}


def _pool(threads: int) -> ThreadPoolExecutor:
    """A pool of ``threads`` threads kept for the process (its start costs about 0.2 ms a call); a forked child
    (a worker process) makes its own, since threads do not survive a fork."""
    key = (os.getpid(), threads)
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix="blocks")
    return _POOLS[key]


__all__ = [
    "closest_point", "closest_walk", "indexed_bounds", "refit_boxes", "rows_bounds", "rows_in_boxes", "run_in_blocks",
    "triangle_distance", "winding_walk",
]  # fmt: skip
