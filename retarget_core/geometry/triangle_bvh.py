"""A bounding-volume tree over one triangle set whose vertices move (a skinned part), built once on the rest
pose and refit per posed frame, queried for many frames at once: exact closest triangles within a distance,
and winding numbers by signed ray crossings (exact for a closed mesh).

Why: libigl builds a tree per call (about 2 ms for 3k triangles on this machine, twice when winding numbers
are wanted too); tested per posed frame, the builds were the collision stage's posed-torso test's cost. Here
the tree's shape is fixed (a complete binary tree down to leaves of a few triangles, split at the centroids'
median), its boxes are refit with a few array reductions per level, and the queries walk it level by level as one
frontier of (query, node) pairs over every frame: no Python loop over frames or nodes (queries go in blocks
that bound the memory). Where few vertices moved since a refit, only their leaves and those leaves' ancestors
are refit again (:func:`refit_changed`); frames posed the same may share their boxes (:attr:`PosedBoxes.rows`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from retarget_core.geometry.bvh_kernels import closest_walk, refit_boxes, run_in_blocks, winding_walk
from retarget_core.geometry.closest_point import closest_points

RAY_DIRECTION = (0.5773, 0.6183, 0.5331)  # winding rays: an oblique direction no mesh edge is drawn along
TIE_M = 1e-12  # closest triangles this close in distance are tied (a shared edge or corner)
QUERY_BLOCK = 8192  # queries walked together: their (query, node) frontier stays within some tens of MB
LEAF_SIZE = 4  # triangles per leaf: with 1, 2, 4 and 8 the whole job read 62, 56, 52 and 52 ms a frame on the bulky
# sample and 185, 165, 153 and 152 on the large character (compiled walks: a refit writes a quarter of the boxes)


@dataclass(frozen=True)
class TriangleBVH:
    """The tree's fixed shape: ``faces (T, 3)`` vertex indices; ``leaf_faces (L, K)`` triangle indices per leaf
    (``L = 2 ** depth`` leaves, padded with -1); every node holds at least one triangle."""

    faces: Tensor
    leaf_faces: Tensor
    depth: int

    def box_bytes(self) -> int:
        """Bytes of one posed frame's boxes (:class:`PosedBoxes`: low and high corners of every node, float64)."""
        return 48 * ((2 << self.depth) - 1)

    def corner(self, level: int, node: Tensor) -> Tensor:
        """``(P,)`` a vertex of a triangle under each of ``node (P,)`` at ``level`` (bounds its distance)."""
        first_leaf = node * (1 << (self.depth - level))
        return self.faces[self.leaf_faces[first_leaf, 0], 0]


@dataclass(frozen=True)
class PosedBoxes:
    """Boxes of every node for ``n`` posed frames in heap order: ``lo, hi (s, H, 3)``, node ``i`` of level ``l``
    (0: the root, ``depth``: the leaves) at ``2 ** l - 1 + i`` (``H = 2 ** (depth + 1) - 1``); ``vertices (s, V,
    3)`` the posed vertices; ``rows (n,)`` the stored row of each frame (None: row ``i`` is frame ``i``): frames
    posed the same are stored once."""

    lo: Tensor
    hi: Tensor
    vertices: Tensor
    rows: Tensor | None = None

    def level(self, level: int) -> slice:
        """The heap's columns of ``level``'s nodes."""
        return slice((1 << level) - 1, (1 << (level + 1)) - 1)


def build_bvh(vertices: np.ndarray, faces: np.ndarray, leaf_size: int = LEAF_SIZE) -> TriangleBVH:
    """The tree over ``faces (T, 3)`` laid out on ``vertices (V, 3)`` (the rest pose): each node's triangles
    split in halves at the median of their centroids along the widest axis."""
    faces = np.asarray(faces, dtype=np.int64)
    t_n = len(faces)
    if t_n == 0:
        raise ValueError("build_bvh: the triangle set is empty")
    depth = max(0, math.ceil(math.log2(max(1.0, t_n / leaf_size))))
    centroid = np.asarray(vertices, dtype=np.float64)[faces].mean(axis=1)
    groups = [np.arange(t_n)]
    for _ in range(depth):
        split = []
        for idx in groups:
            c = centroid[idx]
            order = idx[np.argsort(c[:, int(np.argmax(np.ptp(c, axis=0)))], kind="stable")]
            half = (len(order) + 1) // 2
            split += [order[:half], order[half:]]
        groups = split
    width = max(len(g) for g in groups)
    leaf = np.full((len(groups), width), -1, dtype=np.int64)
    for k, g in enumerate(groups):
        leaf[k, : len(g)] = g
    return TriangleBVH(torch.from_numpy(faces), torch.from_numpy(leaf), depth)


def refit(bvh: TriangleBVH, vertices: Tensor) -> PosedBoxes:
    """Every node's box for posed ``vertices (n, V, 3)`` (on the CPU compiled: :func:`bvh_kernels.refit_boxes`)."""
    vertices = vertices.contiguous()  # the gathers here and in the queries (a part's posed mesh comes vertex-major)
    heap = (2 << bvh.depth) - 1
    lo, hi = vertices.new_empty(len(vertices), heap, 3), vertices.new_empty(len(vertices), heap, 3)
    boxes = PosedBoxes(lo, hi, vertices)
    if vertices.device.type == "cpu":
        arrays = vertices.numpy(), bvh.faces.numpy(), bvh.leaf_faces.numpy(), bvh.depth, lo.numpy(), hi.numpy()
        run_in_blocks(lambda b: refit_boxes(arrays[0][b], *arrays[1:4], arrays[4][b], arrays[5][b]), len(vertices), 8)
        return boxes
    leaves = boxes.level(bvh.depth)
    lo[:, leaves], hi[:, leaves] = _leaf_boxes(bvh, vertices, torch.arange(len(bvh.leaf_faces)))
    for level in range(bvh.depth - 1, -1, -1):
        kids, here = boxes.level(level + 1), boxes.level(level)
        lo[:, here], hi[:, here] = _parent_boxes(lo[:, kids], hi[:, kids])
    return boxes


def refit_changed(bvh: TriangleBVH, vertices: Tensor, base: PosedBoxes, changed: Tensor) -> PosedBoxes:
    """:func:`refit` of posed ``vertices (n, V, 3)`` from ``base``, the boxes of the same ``n`` frames before the
    vertices ``changed (V,)`` (bool) moved: only the leaves with a triangle on a changed vertex and their ancestors
    are computed again (the same min and max: equal to a full refit); ``base`` itself when nothing changed."""
    face_changed = changed[bvh.faces].any(dim=1)  # (T,)
    leaf = bvh.leaf_faces
    leaves = torch.nonzero((face_changed[leaf.clamp_min(0)] & (leaf >= 0)).any(dim=1)).flatten()
    if len(leaves) == 0:
        return base
    if 2 * len(leaves) > len(leaf):  # most of the tree moved: the full refit is cheaper than its copies
        return refit(bvh, vertices)
    vertices = vertices.contiguous()
    boxes = PosedBoxes(_per_frame(base.lo, base.rows), _per_frame(base.hi, base.rows), vertices)
    first = (1 << bvh.depth) - 1
    boxes.lo[:, first + leaves], boxes.hi[:, first + leaves] = _leaf_boxes(bvh, vertices, leaves)
    nodes = leaves
    for level in range(bvh.depth - 1, -1, -1):
        nodes = torch.unique(nodes // 2)
        here = (1 << level) - 1 + nodes
        kids = ((1 << (level + 1)) - 1 + torch.stack([2 * nodes, 2 * nodes + 1], dim=1)).flatten()
        boxes.lo[:, here], boxes.hi[:, here] = _parent_boxes(boxes.lo[:, kids], boxes.hi[:, kids])
    return boxes


def _per_frame(stored: Tensor, rows: Tensor | None) -> Tensor:
    """A copy of ``stored (s, ...)`` with a row per frame (``rows (n,)``: the stored row of each; None: the same)."""
    return stored.clone() if rows is None else stored[rows]


def _leaf_boxes(bvh: TriangleBVH, vertices: Tensor, leaves: Tensor) -> tuple[Tensor, Tensor]:
    """``(n, P, 3)`` low and high corners of ``leaves (P,)`` on posed ``vertices (n, V, 3)`` (an empty leaf:
    +inf and -inf)."""
    face = bvh.leaf_faces[leaves]  # (P, K), -1: padding
    if face.shape[1] == 1:  # one triangle per leaf: its corners' min and max (no reduction over the leaf)
        full = torch.nonzero(face[:, 0] >= 0).flatten()
        tri = bvh.faces[face[full, 0]]  # (P', 3)
        a, b, c = (vertices.index_select(1, tri[:, k]) for k in range(3))
        spot = torch.full((len(leaves),), len(full), dtype=torch.long)  # each leaf's row; empty ones the last (inf)
        spot[full] = torch.arange(len(full))
        empty = vertices.new_full((vertices.shape[0], 1, 3), math.inf)
        lo = torch.cat([torch.minimum(torch.minimum(a, b), c), empty], dim=1).index_select(1, spot)
        hi = torch.cat([torch.maximum(torch.maximum(a, b), c), -empty], dim=1).index_select(1, spot)
        return lo, hi
    corners = vertices[:, bvh.faces[face.clamp_min(0)]]  # (n, P, K, 3, 3); padding repeats triangle 0, masked
    mask = (face < 0)[None, :, :, None]
    lo = corners.amin(dim=3).masked_fill(mask, math.inf).amin(dim=2)
    hi = corners.amax(dim=3).masked_fill(mask, -math.inf).amax(dim=2)
    return lo, hi


def _parent_boxes(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """``(n, P, 3)`` the boxes of the parents of nodes ``lo, hi (n, 2 P, 3)`` (siblings next to each other)."""
    return torch.minimum(lo[:, 0::2], lo[:, 1::2]), torch.maximum(hi[:, 0::2], hi[:, 1::2])


def _leaf_triangles(bvh: TriangleBVH, boxes: PosedBoxes, frame: Tensor, leaf: Tensor) -> tuple[Tensor, Tensor]:
    """For pairs of ``frame, leaf (P,)``: ``face (P, K)`` (-1: padding) and corners ``(P, K, 3, 3)``."""
    face = bvh.leaf_faces[leaf]
    rows = frame[:, None, None] * boxes.vertices.shape[1] + bvh.faces[face.clamp_min(0)]  # (P, K, 3)
    return face, boxes.vertices.reshape(-1, 3)[rows]


def _distances(p: Tensor, corners: Tensor) -> Tensor:
    """``(P, K)`` exact distance of points ``p (P, 3)`` to triangles ``corners (P, K, 3, 3)``."""
    k = corners.shape[1]
    flat = corners.reshape(-1, 3, 3)
    x = p[:, None].expand(-1, k, -1).reshape(-1, 3)
    return (x - closest_points(x, flat[:, 0], flat[:, 1], flat[:, 2])).norm(dim=-1).reshape(-1, k)


def _node_boxes(boxes: PosedBoxes, level: int, key: Tensor) -> tuple[Tensor, Tensor]:
    """``(P, 3)`` the boxes of nodes ``key (P,)`` (frame ``* 2 ** level +`` node) at ``level``."""
    at = (key >> level) * boxes.lo.shape[1] + (1 << level) - 1 + (key & ((1 << level) - 1))
    return boxes.lo.reshape(-1, 3)[at], boxes.hi.reshape(-1, 3)[at]


def _box_distance(p: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """``(P,)`` distance of points ``p (P, 3)`` to boxes ``lo, hi (P, 3)`` (0 inside)."""
    return (torch.clamp(lo - p, min=0.0) + torch.clamp(p - hi, min=0.0)).norm(dim=-1)


def closest_triangles(bvh: TriangleBVH, boxes: PosedBoxes, frame: Tensor, points: Tensor,
                      max_distance: float | Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Exact distance ``(Q,)`` from ``points (Q, 3)`` (posed frame ``frame (Q,)``) to the triangles, and the
    closest triangle ``(Q,)`` (the lowest index where several are: a point nearest a shared edge); ``inf`` and -1
    where none is within ``max_distance`` (one for all, or ``(Q,)``: a tighter bound prunes the walk sooner).
    On the CPU the compiled walk answers (:mod:`retarget_core.geometry.bvh_kernels`), elsewhere the tensor walk
    (:func:`tensor_closest_triangles`)."""
    rows = frame if boxes.rows is None else boxes.rows[frame]
    limit = torch.as_tensor(max_distance, dtype=points.dtype).expand(len(points))
    if points.device.type != "cpu":
        return tensor_closest_triangles(bvh, replace(boxes, rows=None), rows, points, limit)
    verts = boxes.vertices
    pts, lim = points.to(verts.dtype).contiguous().numpy(), limit.to(verts.dtype).contiguous().numpy()
    distance, face = np.empty(len(pts), dtype=pts.dtype), np.empty(len(pts), dtype=np.int64)
    arrays = _walk_arrays(bvh, boxes)
    rows_np = rows.contiguous().numpy()

    def walk(b: slice) -> None:
        closest_walk(*arrays, rows_np[b], pts[b], lim[b], TIE_M, distance[b], face[b])

    run_in_blocks(walk, len(pts))
    return torch.from_numpy(distance).to(points.dtype), torch.from_numpy(face)


def _walk_arrays(
    bvh: TriangleBVH, boxes: PosedBoxes
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The arrays the compiled walks read: boxes, vertices, faces, leaves and depth."""
    return (boxes.lo.contiguous().numpy(), boxes.hi.contiguous().numpy(), boxes.vertices.contiguous().numpy(),
            bvh.faces.numpy(), bvh.leaf_faces.numpy(), bvh.depth)  # fmt: skip


def tensor_closest_triangles(bvh: TriangleBVH, boxes: PosedBoxes, frame: Tensor, points: Tensor,
                             max_distance: float | Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
    """:func:`closest_triangles` walked level by level as one frontier of (query, node) pairs over every frame, in
    tensor operations (any device; the compiled walk's reference). Blocks of :data:`QUERY_BLOCK` queries bound
    the memory."""
    if boxes.rows is not None:
        return tensor_closest_triangles(bvh, replace(boxes, rows=None), boxes.rows[frame], points, max_distance)
    q_n = len(points)
    limit = torch.as_tensor(max_distance, dtype=points.dtype).expand(q_n)
    if q_n > QUERY_BLOCK:
        parts = [tensor_closest_triangles(bvh, boxes, frame[s : s + QUERY_BLOCK], points[s : s + QUERY_BLOCK],
                                          limit[s : s + QUERY_BLOCK]) for s in range(0, q_n, QUERY_BLOCK)]  # fmt: skip
        return torch.cat([d for d, _ in parts]), torch.cat([f for _, f in parts])
    flat = boxes.vertices.reshape(-1, 3)
    v_n = boxes.vertices.shape[1]
    bound = limit.clone()
    pair_q, key = torch.arange(q_n), frame.clone()  # key: the pair's box row, frame * 2 ** level + node
    for level in range(bvh.depth + 1):
        at = points[pair_q]
        near = _box_distance(at, *_node_boxes(boxes, level, key))
        pf, node = key >> level, key & ((1 << level) - 1)
        far = (at - flat[pf * v_n + bvh.corner(level, node)]).norm(dim=-1)  # a surface point's
        bound = bound.scatter_reduce(0, pair_q, far, "amin")
        keep = torch.nonzero(near <= bound[pair_q]).flatten()
        pair_q, key, near = pair_q[keep], key[keep], near[keep]
        if level < bvh.depth:
            pair_q, key = pair_q.repeat_interleave(2), torch.stack([2 * key, 2 * key + 1], dim=1).flatten()
    node = key & ((1 << bvh.depth) - 1)
    pair_q, node = _nearest_leaf_first(bvh, boxes, frame, points, pair_q, node, near, bound)
    face, corners = _leaf_triangles(bvh, boxes, frame[pair_q], node)
    d = _distances(points[pair_q], corners)
    d = d.masked_fill(face < 0, math.inf).nan_to_num(nan=math.inf)
    best = points.new_full((q_n,), math.inf).scatter_reduce(0, pair_q, d.amin(dim=1), "amin")
    best = torch.where(best <= limit, best, torch.full_like(best, math.inf))
    tied = d <= (best[pair_q] + TIE_M)[:, None]  # of closest triangles tied at an edge or corner, the lowest index
    none = len(bvh.faces)
    first = torch.where(tied, face, torch.full_like(face, none)).amin(dim=1)
    out_face = torch.full((q_n,), none, dtype=torch.long).scatter_reduce(0, pair_q, first, "amin")
    return best, out_face.masked_fill((out_face == none) | torch.isinf(best), -1)


def _nearest_leaf_first(bvh: TriangleBVH, boxes: PosedBoxes, frame: Tensor, points: Tensor, pair_q: Tensor,
                        leaf: Tensor, near: Tensor, bound: Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
    """The (query, leaf) pairs ``pair_q, leaf (P,)`` (box distances ``near``) that can still hold the closest
    triangle once each query's nearest box has been searched exactly (its distance bounds the others)."""
    if len(pair_q) == 0:
        return pair_q, leaf
    # each query's first pair in walk order (what the pairs sorted by ``near`` gave too: the smallest index)
    first = torch.full_like(bound, len(pair_q), dtype=torch.long).scatter_reduce(
        0, pair_q, torch.arange(len(pair_q)), "amin")  # fmt: skip
    has = first < len(pair_q)
    rows = first[has]
    face, corners = _leaf_triangles(bvh, boxes, frame[pair_q[rows]], leaf[rows])
    d = _distances(points[pair_q[rows]], corners)
    bound = bound.clone()
    bound[has] = torch.minimum(bound[has], d.masked_fill(face < 0, math.inf).nan_to_num(nan=math.inf).amin(dim=1))
    keep = near <= bound[pair_q] + TIE_M
    return pair_q[keep], leaf[keep]


def _ray_hits_box(o: Tensor, inv_dir: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """``(P,)`` the rays from ``o (P, 3)`` along the fixed direction (``inv_dir (3,)``) meet boxes ``lo, hi``."""
    t1, t2 = (lo - o) * inv_dir, (hi - o) * inv_dir
    t_in = torch.minimum(t1, t2).amax(dim=-1)
    t_out = torch.maximum(t1, t2).amin(dim=-1)
    return t_out >= t_in.clamp_min(0.0)


def _ray_crossings(o: Tensor, direction: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """``(...)`` +1 / -1 where the ray from ``o (..., 3)`` along ``direction (3,)`` crosses triangle ``a, b, c``
    (by its orientation), 0 where it misses (Moller-Trumbore)."""
    e1, e2 = b - a, c - a
    pvec = torch.cross(direction.expand_as(e2), e2, dim=-1)
    det = (e1 * pvec).sum(-1)
    inv = 1.0 / torch.where(det.abs() > 1e-300, det, torch.full_like(det, 1e-300))
    tvec = o - a
    u = (tvec * pvec).sum(-1) * inv
    qvec = torch.cross(tvec, e1, dim=-1)
    v = (direction * qvec).sum(-1) * inv
    t = (e2 * qvec).sum(-1) * inv
    hit = (det.abs() > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return torch.where(hit, torch.sign(det), torch.zeros_like(det))


def winding_numbers(bvh: TriangleBVH, boxes: PosedBoxes, frame: Tensor, points: Tensor) -> Tensor:
    """``(Q,)`` the signed count of triangles a ray from each of ``points (Q, 3)`` (posed frame ``frame (Q,)``)
    crosses: the winding number of a closed mesh (+-1 inside an outward or inward oriented one, 0 outside). On
    the CPU the compiled walk answers, elsewhere the tensor walk (:func:`tensor_winding_numbers`)."""
    rows = frame if boxes.rows is None else boxes.rows[frame]
    if points.device.type != "cpu":
        return tensor_winding_numbers(bvh, replace(boxes, rows=None), rows, points)
    verts = boxes.vertices
    pts = points.to(verts.dtype).contiguous().numpy()
    direction = np.asarray(RAY_DIRECTION, dtype=pts.dtype)
    direction = direction / np.linalg.norm(direction)
    out = np.empty(len(pts), dtype=pts.dtype)
    arrays = _walk_arrays(bvh, boxes)
    rows_np = rows.contiguous().numpy()

    def walk(b: slice) -> None:
        winding_walk(*arrays, rows_np[b], pts[b], direction, out[b])

    run_in_blocks(walk, len(pts))
    return torch.from_numpy(out).to(points.dtype)


def tensor_winding_numbers(bvh: TriangleBVH, boxes: PosedBoxes, frame: Tensor, points: Tensor) -> Tensor:
    """:func:`winding_numbers` walked level by level in tensor operations (any device; the compiled walk's
    reference)."""
    if boxes.rows is not None:
        return tensor_winding_numbers(bvh, replace(boxes, rows=None), boxes.rows[frame], points)
    if len(points) > QUERY_BLOCK:
        return torch.cat([tensor_winding_numbers(bvh, boxes, frame[s : s + QUERY_BLOCK], points[s : s + QUERY_BLOCK])
                          for s in range(0, len(points), QUERY_BLOCK)])  # fmt: skip
    direction = points.new_tensor(RAY_DIRECTION)
    direction = direction / direction.norm()
    inv_dir = 1.0 / direction
    q_n = len(points)
    pair_q, key = torch.arange(q_n), frame.clone()  # key: the pair's box row, frame * 2 ** level + node
    for level in range(bvh.depth + 1):
        lo, hi = _node_boxes(boxes, level, key)
        keep = torch.nonzero(_ray_hits_box(points[pair_q], inv_dir, lo, hi)).flatten()
        pair_q, key = pair_q[keep], key[keep]
        if level < bvh.depth:
            pair_q, key = pair_q.repeat_interleave(2), torch.stack([2 * key, 2 * key + 1], dim=1).flatten()
    node = key & ((1 << bvh.depth) - 1)
    face, corners = _leaf_triangles(bvh, boxes, frame[pair_q], node)
    cross = _ray_crossings(
        points[pair_q][:, None], direction, corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    )
    cross = cross.masked_fill(face < 0, 0.0).sum(dim=1)
    return points.new_zeros(q_n).index_add(0, pair_q, cross)


__all__ = ["PosedBoxes", "TriangleBVH", "build_bvh", "closest_triangles", "refit", "refit_changed",
           "tensor_closest_triangles", "tensor_winding_numbers", "winding_numbers"]  # fmt: skip
