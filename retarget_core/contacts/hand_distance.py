"""Distance from each hand to each other body part's surface, 0 when inside (ACCEPTANCE.md "Hand self-contact").

Parts are the six clusters of :data:`retarget_core.body_parts.CLUSTERS` (head, torso, each arm, each leg): the
triangles whose dominant segment is in the cluster, closed by a fan over every open boundary loop
(:func:`~retarget_core.energy.mesh_distance.cap_boundary_loops`), so every part is a closed volume. Hand vertices
are those whose dominant segment is a hand (fingers included). Per frame and (hand, part):

    d = 0                                  when a hand vertex lies inside the part's closed volume,
    d = min over hand vertices p of dist(p, part surface)   otherwise,

exact (point-triangle distances) up to ``max_distance``, ``inf`` beyond it. A hand's own arm is not measured
(``inf``): the hand is attached to it.

How (flat tensors over blocks of frames, no per-pair Python loop):

1. every bound is computed on the posed frame: spheres around chunks of at most 32 hand vertices and chunks of at
   most 32 triangles of one part (grouped once by rest-pose voxels; skinning cannot invalidate the bounds, since
   centres and radii are measured per frame);
2. culling in four levels, each keeping what can still beat the group's best upper bound plus ``slack``:
   triangle chunk against the hand's box grown by ``max_distance``; (hand chunk, triangle chunk);
   (hand chunk, triangle); (hand vertex, triangle);
3. exact closest points (Ericson, Real-Time Collision Detection 5.1.5) on what is left; a vertex is inside when
   ``(p - q) . n`` summed over the triangles tied at its closest point ``q`` is negative (the pseudonormal test:
   exact on faces and edges, equal weights instead of angle weights at vertices). The slack (5 mm at 1.80 m, the
   median hand edge) makes the test reach the vertices of a hand triangle that crosses the surface, so a hand
   partly sunk into the body reads 0, and a fully sunk one reads 0 too (its nearest vertex is inside).

Most of the time goes to the triangle chunks' spheres, the KD-tree queries and, while a hand rests on the body,
the exact closest points of every hand vertex within the slack.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, HAND_SEGMENTS, BodyParts
from retarget_core.character import Character
from retarget_core.energy.mesh_distance import cap_boundary_loops
from retarget_core.energy.sdf import vertex_clusters
from retarget_core.geometry.closest_point import closest_points

REFERENCE_HEIGHT_M = 1.80
OWN_ARM: dict[str, str] = {"LeftHand": "left_arm", "RightHand": "right_arm"}


@dataclass(frozen=True)
class HandDistanceParams:
    """Lengths at a 1.80 m character (scaled to the body's height)."""

    # Exact below this, inf above: covers the acceptance figures (contact below 1.5 cm, kept below 2.5 cm, "away"
    # above 3 cm; a false contact's source distance is above 5 cm: inf); larger values cost more culling work.
    max_distance_m: float = 0.05
    # Vertices this much farther than the closest one are also evaluated exactly: the median hand edge (5 mm on
    # the MakeHuman hand), so the inside test reaches the vertices of a hand triangle crossing the surface.
    slack_m: float = 0.005
    # Rest-pose voxel edge of the hand and triangle chunks (efficiency only, results do not depend on it).
    hand_chunk_m: float = 0.03
    triangle_chunk_m: float = 0.06
    chunk_members: int = 32
    # Triangles within this of a vertex's closest distance share its closest point (a face, edge or vertex).
    tie_m: float = 1e-7
    # Closest (hand vertex, part vertex) pairs kept per (frame, hand, part).
    pairs: int = 3
    frames_per_block: int = 16


@dataclass
class HandPartGeometry:
    """What the distance queries need of one body, built once (:func:`hand_part_geometry`).

    faces: ``(T, 3)`` triangles of all parts, caps included, into the vertices followed by one centre per cap.
    face_part: ``(T,)`` part (index into :data:`CLUSTERS`) of each triangle.
    ring_vertex, ring_cap: ``(R,)`` vertices of every cap's loop and the cap they belong to (a cap's centre is
        the mean of its loop, posed per frame); ring_count ``(C,)``.
    hand_vertices: per hand, its vertex indices ``(N_h,)``.
    hand_chunks: ``(H, K)`` vertex indices of each hand chunk (-1 padded); hand_chunk_hand ``(H,)``.
    chunks_of_hand: ``(2, M)`` the hand chunks of each hand (-1 padded).
    tri_chunks: ``(Q, K)`` triangles of each triangle chunk (-1 padded); tri_chunk_part ``(Q,)``;
        tri_chunk_vertices ``(Q, L)`` their vertices (-1 padded).
    measured: ``(2, P)`` the (hand, part) pairs measured (not the hand's own arm, both present).
    """

    num_vertices: int
    hands: tuple[str, ...]
    parts: tuple[str, ...]
    faces: Tensor
    face_part: Tensor
    ring_vertex: Tensor
    ring_cap: Tensor
    ring_count: Tensor
    hand_vertices: list[Tensor]
    hand_chunks: Tensor
    hand_chunk_hand: Tensor
    chunks_of_hand: Tensor
    tri_chunks: Tensor
    tri_chunk_part: Tensor
    tri_chunk_vertices: Tensor
    measured: Tensor
    tri_chunk_members: tuple[Tensor, Tensor, Tensor]
    hand_chunk_dense: Tensor
    hand_local: Tensor
    hand_width: int
    hand_flat: Tensor = field(init=False)  # (N,) the hands' vertices, hand after hand
    hand_starts: Tensor = field(init=False)  # (2,) where each hand starts in hand_flat
    hand_sizes: Tensor = field(init=False)  # (2,) vertices per hand

    def __post_init__(self) -> None:
        self.hand_sizes = torch.tensor([len(v) for v in self.hand_vertices], dtype=torch.long)
        self.hand_starts = torch.cumsum(self.hand_sizes, 0) - self.hand_sizes
        self.hand_flat = torch.cat(self.hand_vertices) if self.hand_vertices else torch.zeros(0, dtype=torch.long)


@dataclass
class HandPartDistances:
    """Hand-to-part distances of a clip.

    distance: ``(F, 2, P)`` metres, 0 when inside, ``inf`` beyond ``max_distance`` or not measured; hands in
        ``hands`` order (LeftHand, RightHand), parts in ``parts`` order (:data:`CLUSTERS`).
    inside: ``(F, 2, P)`` a hand vertex lies inside the part's closed volume.
    pairs: ``(F, 2, P, K, 2)`` the K hand vertices closest to the part (distinct), each with the part vertex
        nearest its closest surface point; -1 where the distance is ``inf``.
    pair_distance: ``(F, 2, P, K)`` distance of each pair's hand vertex to the part surface (m).
    measured: ``(2, P)`` pairs measured at all.
    """

    hands: tuple[str, ...]
    parts: tuple[str, ...]
    distance: Tensor
    inside: Tensor
    pairs: Tensor
    pair_distance: Tensor
    measured: Tensor
    max_distance: float

    @property
    def num_frames(self) -> int:
        return int(self.distance.shape[0])

    def nearest(self) -> Tensor:
        """``(F, 2)`` each hand's distance to the nearest other part."""
        return self.distance.amin(-1)


def _padded(groups: list[np.ndarray], width: int | None = None) -> Tensor:
    width = width or max((len(g) for g in groups), default=1)
    out = np.full((len(groups), max(width, 1)), -1, dtype=np.int64)
    for i, g in enumerate(groups):
        out[i, : len(g)] = g
    return torch.from_numpy(out)


def _chunks(points: Tensor, label: Tensor, size: float, members: int) -> tuple[Tensor, Tensor]:
    """Groups ``(C, K)`` (-1 padded, indices into ``points``) of points of one label each, and their labels."""
    cl = vertex_clusters(points.double(), label, size, members)
    return cl.members, cl.part


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def hand_part_geometry(parts: BodyParts, vertices: Tensor, height: float | None = None,
                       params: HandDistanceParams | None = None) -> HandPartGeometry:  # fmt: skip
    """The closed parts, caps and chunks of a body; ``vertices (V, 3)``: any pose of it (the rest pose), used for
    the caps' orientation and the chunk layout only."""
    params = params or HandDistanceParams()
    height = height or float(vertices[:, 1].max() - vertices[:, 1].min())
    s = height / REFERENCE_HEIGHT_M
    v_np = vertices.detach().double().numpy()
    n_v = len(v_np)
    faces = parts.faces.numpy().astype(np.int64)
    seg_cluster = np.asarray(parts.cluster, dtype=np.int64)
    face_cluster = seg_cluster[parts.face_part.numpy()]
    all_faces, all_part, rings, ring_caps = [], [], [], []
    centres: list[np.ndarray] = []
    for c in range(len(CLUSTERS)):
        pf = faces[face_cluster == c]
        if len(pf) == 0:
            continue
        cv, cf = cap_boundary_loops(v_np, pf)
        if _signed_volume(cv, cf) < 0:  # inward-facing mesh: flip so normals point out
            cf = cf[:, [0, 2, 1]]
        # Caps' centres are the new vertices n_v.. of cv; renumber them after the centres of earlier parts.
        extra = cf >= n_v
        base = n_v + len(centres)
        caps = cf[extra.any(1)]
        for local in range(len(cv) - n_v):
            ring = np.unique(caps[(caps == n_v + local).any(1)])
            ring = ring[ring < n_v]
            rings.append(ring)
            ring_caps.append(np.full(len(ring), len(centres)))
            centres.append(cv[n_v + local])
        cf = np.where(extra, cf - n_v + base, cf)
        all_faces.append(cf)
        all_part.append(np.full(len(cf), c))
    faces_t = torch.from_numpy(np.concatenate(all_faces))
    face_part = torch.from_numpy(np.concatenate(all_part))
    ring_vertex = torch.from_numpy(np.concatenate(rings)) if rings else torch.zeros(0, dtype=torch.long)
    ring_cap = torch.from_numpy(np.concatenate(ring_caps)) if rings else torch.zeros(0, dtype=torch.long)
    ring_count = torch.bincount(ring_cap, minlength=len(centres))
    ext = np.concatenate([v_np, np.asarray(centres).reshape(-1, 3)])
    # Hands.
    hands = tuple(HAND_SEGMENTS)
    hand_vertices = []
    for h in hands:
        seg = parts.find(h)
        hand_vertices.append(parts.part_vertices(seg) if seg is not None else torch.zeros(0, dtype=torch.long))
    hv = torch.cat(hand_vertices)
    hl = torch.cat([torch.full((len(x),), i, dtype=torch.long) for i, x in enumerate(hand_vertices)])
    if len(hv):
        members, chunk_hand = _chunks(vertices[hv], hl, params.hand_chunk_m * s, params.chunk_members)
        hand_chunks = torch.where(members >= 0, hv[members.clamp_min(0)], members)
    else:
        hand_chunks, chunk_hand = torch.full((0, 1), -1, dtype=torch.long), torch.zeros(0, dtype=torch.long)
    chunks_of_hand = _padded([np.nonzero(chunk_hand.numpy() == i)[0] for i in range(len(hands))])
    # Triangle chunks by rest centroid.
    centroid = torch.from_numpy(ext[faces_t.numpy()].mean(1))
    tri_chunks, tri_chunk_part = _chunks(centroid, face_part, params.triangle_chunk_m * s, params.chunk_members)
    tri_chunk_vertices = _padded(
        [np.unique(faces_t.numpy()[m[m >= 0]]) for m in tri_chunks.numpy()]
    )
    hand_local = torch.full((n_v,), -1, dtype=torch.long)
    for v in hand_vertices:
        hand_local[v] = torch.arange(len(v))
    measured = torch.zeros(len(hands), len(CLUSTERS), dtype=torch.bool)
    present = torch.zeros(len(CLUSTERS), dtype=torch.bool)
    present[face_part.unique()] = True
    for i, h in enumerate(hands):
        if len(hand_vertices[i]):
            measured[i] = present
            measured[i, CLUSTERS.index(OWN_ARM[h])] = False
    return HandPartGeometry(
        n_v, hands, tuple(CLUSTERS), faces_t, face_part, ring_vertex, ring_cap, ring_count, hand_vertices,
        hand_chunks, chunk_hand, chunks_of_hand, tri_chunks, tri_chunk_part, tri_chunk_vertices, measured,
        _memberships(tri_chunk_vertices), _dense(hand_chunks), hand_local, max((len(v) for v in hand_vertices), default=1),
    )  # fmt: skip


def _dense(members: Tensor) -> Tensor:
    """A -1 padded table ``(C, K)`` padded with each row's first member instead (for bounding boxes)."""
    return torch.where(members >= 0, members, members[:, :1])


def _flat_sphere(x: Tensor, group: Tensor, member: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
    """Centre ``(B, C, 3)`` (mean) and radius ``(B, C)`` of the posed points ``x (B, N, 3)`` of each group
    (flat memberships ``group``, ``member`` ``(M,)``, ``group`` sorted; ``count (C,)`` members per group): cheaper
    than :func:`_sphere` for groups of very different sizes."""
    bsz = x.shape[0]
    rows = x.transpose(0, 1).reshape(x.shape[1], bsz * 3)  # one row per point: gathers and sums run on rows
    pts = rows.index_select(0, member)  # (M, B*3)
    centre = torch.zeros(len(count), bsz * 3, dtype=x.dtype).index_add_(0, group, pts)
    centre = centre / count.clamp_min(1).to(x.dtype)[:, None]
    spread = (pts - centre.index_select(0, group)).view(-1, bsz, 3).norm(dim=-1)  # (M, B)
    r = torch.segment_reduce(spread, "max", lengths=count, axis=0).clamp_min(0.0)  # an empty group: 0
    return centre.view(-1, bsz, 3).transpose(0, 1), r.transpose(0, 1)


def _memberships(members: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The valid entries of a -1 padded table ``(C, K)``: group ``(M,)``, member ``(M,)``, count ``(C,)``."""
    ok = members >= 0
    group = torch.arange(len(members))[:, None].expand_as(members)[ok]
    return group, members[ok], torch.bincount(group, minlength=len(members))


def _sphere(x: Tensor, members: Tensor) -> tuple[Tensor, Tensor]:
    """Centre ``(B, C, 3)`` (of the bounding box) and radius ``(B, C)`` of the posed points ``x (B, N, 3)`` of
    each group of ``members (C, K)`` (padded with repeats, see :func:`_dense`)."""
    pts = x[:, members]  # (B, C, K, 3)
    centre = 0.5 * (pts.amax(2) + pts.amin(2))
    return centre, (pts - centre[:, :, None]).norm(dim=-1).amax(-1)


def _group_min(values: Tensor, group: Tensor, size: int, init: Tensor | None = None) -> Tensor:
    out = torch.full((size,), float("inf"), dtype=values.dtype) if init is None else init.clone()
    return out.scatter_reduce(0, group, values, "amin")


def _expand(table: Tensor, rows: Tensor, *carry: Tensor) -> tuple[Tensor, ...]:
    """Each row index of ``rows (N,)`` replaced by the valid members of ``table[rows] (N, K)`` (-1 padded), with
    ``carry`` tensors ``(N,)`` repeated alongside: returns (members, *carried), each ``(M,)``."""
    members = table[rows]
    ok = members >= 0
    return (members[ok], *(c[:, None].expand_as(members)[ok] for c in carry))


def _argmin_by_group(values: Tensor, group: Tensor, size: int) -> Tensor:
    """For each of ``size`` groups, the index of its entry with the smallest value (the first on ties)."""
    low = _group_min(values, group, size)
    idx = torch.where(values <= low[group], torch.arange(len(values)), len(values))
    return torch.full((size,), len(values), dtype=torch.long).scatter_reduce(0, group, idx, "amin")


def _ranked(key: Tensor, value: Tensor) -> tuple[Tensor, Tensor]:
    """Entries ordered by ``key`` then ``value``, and each one's rank within its key: (order, rank)."""
    order = torch.argsort(value, stable=True)
    order = order[torch.argsort(key[order], stable=True)]
    _, counts = torch.unique_consecutive(key[order], return_counts=True)
    rank = torch.arange(len(order)) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    return order, rank


class _HandTree:
    """Nearest hand vertex of a block of frames: one KD-tree (scipy cKDTree) over both hands of every frame, each
    (frame, hand) shifted to a cell of its own, far from the others."""

    def __init__(self, x: Tensor, geom: HandPartGeometry, cells: Tensor) -> None:
        span = float((x.amax((0, 1)) - x.amin((0, 1))).max()) + 1.0
        self.step = 4.0 * span  # a query in its own cell is nearer to it than to any other cell
        self.hands = len(geom.hands)
        # Only the (frame, hand) cells that are queried, each cell's vertices in its hand's order.
        hand = cells % self.hands
        sizes = geom.hand_sizes[hand]
        cell_of_point = torch.repeat_interleave(cells, sizes)
        within = torch.arange(int(sizes.sum())) - torch.repeat_interleave(torch.cumsum(sizes, 0) - sizes, sizes)
        vertex = geom.hand_flat[geom.hand_starts[cell_of_point % self.hands] + within]
        self.vertex = vertex.numpy()
        pts = x.reshape(-1, 3).index_select(0, (cell_of_point // self.hands) * x.shape[1] + vertex).numpy()
        self.tree = cKDTree(pts + self._offset(cell_of_point.numpy()))

    def _offset(self, cells: np.ndarray) -> np.ndarray:
        out = np.zeros((len(cells), 3))
        out[:, 0] = cells * self.step
        return out

    def within(self, points: Tensor, b: Tensor, h: Tensor, radius: Tensor) -> tuple[Tensor, Tensor]:
        """Hand vertices (body indices) within ``radius (N,)`` of ``points (N, 3)`` (frame ``b``, hand ``h``), as
        flat (vertex ``(M,)``, index of the point ``(M,)``)."""
        if len(points) == 0:
            return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long)
        cells = (b * self.hands + h).numpy()
        found = self.tree.query_ball_point(points.numpy() + self._offset(cells), radius.numpy(), return_sorted=False)
        counts = np.fromiter((len(f) for f in found), dtype=np.int64, count=len(found))
        flat = np.fromiter(itertools.chain.from_iterable(found), dtype=np.int64, count=int(counts.sum()))
        owner = np.repeat(np.arange(len(found)), counts)
        return torch.from_numpy(self.vertex[flat]), torch.from_numpy(owner)

    def distance(self, points: Tensor, b: Tensor, h: Tensor) -> Tensor:
        """Distance ``(N,)`` from ``points (N, 3)`` of frames ``b (N,)`` to the nearest vertex of hand ``h (N,)``."""
        return self.nearest(points, b, h)[0]

    def nearest(self, points: Tensor, b: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
        """Distance ``(N,)`` and body index ``(N,)`` of the nearest vertex of hand ``h (N,)`` in frame ``b (N,)``."""
        if len(points) == 0:
            return torch.zeros(0, dtype=points.dtype), torch.zeros(0, dtype=torch.long)
        cells = (b * self.hands + h).numpy()
        d, i = self.tree.query(points.numpy() + self._offset(cells), k=1)
        return torch.from_numpy(np.asarray(d, dtype=np.float64)).to(points.dtype), torch.from_numpy(self.vertex[i])


@dataclass
class _Block:
    """One block of frames under :func:`_block_distances`: posed ``x (B, V, 3)`` and ``ext (B, V + caps, 3)``
    (cap centres appended), ``n_g`` (frame, hand, part) groups, the triangle chunks' spheres ``tc_c (B, Q, 3)``,
    ``tc_r (B, Q)``, and each group's running upper bound ``upper (n_g,)`` on its distance."""

    geom: HandPartGeometry
    x: Tensor
    ext: Tensor
    n_g: int
    cutoff: float
    slack: float
    params: HandDistanceParams
    tc_c: Tensor
    tc_r: Tensor
    upper: Tensor = field(default_factory=lambda: torch.zeros(0))


def _block_distances(geom: HandPartGeometry, x: Tensor, cutoff: float, slack: float, params: HandDistanceParams
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """One block of frames ``x (B, V, 3)`` (float64): distance, inside ``(B, 2, P)``, pairs ``(B, 2, P, K, 2)``,
    pair distances ``(B, 2, P, K)``."""
    bsz, n_h, n_p, k_pairs = x.shape[0], len(geom.hands), len(geom.parts), params.pairs
    shape = (bsz, n_h, n_p)
    n_g = bsz * n_h * n_p
    n_caps = len(geom.ring_count)
    centres = torch.zeros(bsz, n_caps, 3, dtype=x.dtype).index_add_(1, geom.ring_cap, x[:, geom.ring_vertex])
    ext = torch.cat([x, centres / geom.ring_count.clamp_min(1).to(x.dtype)[None, :, None]], dim=1)
    blk = _Block(geom, x, ext, n_g, cutoff, slack, params, *_flat_sphere(ext, *geom.tri_chunk_members))
    near = _chunks_near_hands(blk)
    if near is None:
        dist_g = torch.full((n_g,), float("inf"), dtype=x.dtype)
        inside_g = torch.zeros(n_g, dtype=torch.bool)
        pairs = torch.full((n_g, k_pairs, 2), -1, dtype=torch.long)
        pair_d = torch.full((n_g, k_pairs), float("inf"), dtype=x.dtype)
    else:
        nearest = _HandTree(x, geom, torch.unique(near[0] * n_h + near[1]))
        rows = _vertex_triangle_rows(blk, nearest, *_triangle_candidates(blk, nearest, *near))
        dist_g, inside_g, pairs, pair_d = _group_results(blk, *rows)
    return dist_g.view(shape), inside_g.view(shape), pairs.view(*shape, k_pairs, 2), pair_d.view(*shape, k_pairs)


def _chunks_near_hands(blk: _Block) -> tuple[Tensor, Tensor, Tensor] | None:
    """Level A: (frame, hand, triangle chunk) ``(N,)`` each whose chunk sphere reaches the hand's box grown by the
    cutoff; None when there are none."""
    x, geom = blk.x, blk.geom
    boxes = [(x[:, v].amin(1), x[:, v].amax(1)) if len(v) else (x[:, 0], x[:, 0]) for v in geom.hand_vertices]
    lo, hi = torch.stack([bx[0] for bx in boxes], 1), torch.stack([bx[1] for bx in boxes], 1)  # (B, 2, 3)
    clamped = torch.maximum(torch.minimum(blk.tc_c[:, None], hi[:, :, None]), lo[:, :, None])
    near = ((blk.tc_c[:, None] - clamped).norm(dim=-1) - blk.tc_r[:, None] <= blk.cutoff)
    near &= geom.measured[:, geom.tri_chunk_part][None]
    b, h, q = near.nonzero(as_tuple=True)
    return None if len(b) == 0 else (b, h, q)


def _triangle_candidates(blk: _Block, nearest: _HandTree, b: Tensor, h: Tensor, q: Tensor
                         ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """Levels B and C: the (frame ``b``, hand ``h``, group ``g``, triangle ``t``) rows ``(N,)`` each that can still
    beat their group's upper bound (left in ``blk.upper``), with each triangle's posed centroid ``(N, 3)`` and
    radius ``(N,)``."""
    geom, ext, slack, cutoff, n_g = blk.geom, blk.ext, blk.slack, blk.cutoff, blk.n_g
    n_h, n_p = len(geom.hands), len(geom.parts)
    tc_c, tc_r = blk.tc_c, blk.tc_r
    g = (b * n_h + h) * n_p + geom.tri_chunk_part[q]
    # Level B: triangle chunks by the distance from their centre to the nearest hand vertex (KD-tree), against a
    # tight upper bound: the chunk vertices of each group's most promising chunk (vertex to vertex).
    dn = nearest.distance(tc_c[b, q], b, h)
    lower = dn - tc_r[b, q]
    upper = _group_min(dn + tc_r[b, q], g, n_g)
    best = _argmin_by_group(lower, g, n_g)
    best = best[best < len(lower)]
    verts = geom.tri_chunk_vertices[q[best]]  # (S, L)
    ok = verts >= 0
    vb = b[best][:, None].expand_as(verts)[ok]
    probe = nearest.distance(ext[vb, verts[ok]], vb, h[best][:, None].expand_as(verts)[ok])
    upper = _group_min(probe, g[best][:, None].expand_as(verts)[ok], n_g, upper)
    keep = lower <= torch.clamp(upper[g], max=cutoff) + slack
    b, h, q, g, dq = b[keep], h[keep], q[keep], g[keep], dn[keep]
    # Level C: their triangles, the same way (a triangle's centroid is on the surface: an upper bound too).
    t, b, h, g, j = _expand(geom.tri_chunks, q, b, h, g, torch.arange(len(q)))
    tri = ext[b[:, None], geom.faces[t]]  # (N, 3, 3)
    t_c = tri.mean(1)
    t_r = (tri - t_c[:, None]).norm(dim=-1).amax(-1)
    # Triangles that the chunk's nearest hand distance already puts beyond the bound are not queried: their own
    # query could neither pass the test below nor lower the bound (triangle inequality, 1 nm for rounding).
    reach = dq[j] - (t_c - tc_c[b, q[j]]).norm(dim=-1) - t_r <= upper[g] + slack + 1e-9
    b, h, g, t, t_c, t_r, tri = (y[reach] for y in (b, h, g, t, t_c, t_r, tri))
    dn, vn = nearest.nearest(t_c, b, h)
    upper = _group_min(dn, g, n_g, upper)
    keep = dn - t_r <= upper[g] + slack
    b, h, g, t, t_c, t_r, tri, vn, dn = (y[keep] for y in (b, h, g, t, t_c, t_r, tri, vn, dn))
    # The exact distance of each triangle to that nearest hand vertex tightens the bound to about the answer.
    exact = (blk.x[b, vn] - closest_points(blk.x[b, vn], tri[:, 0], tri[:, 1], tri[:, 2])).norm(dim=-1)
    blk.upper = _group_min(exact, g, n_g, upper)
    keep = dn - t_r <= blk.upper[g] + slack
    return b[keep], h[keep], g[keep], t[keep], t_c[keep], t_r[keep]


def _vertex_triangle_rows(blk: _Block, nearest: _HandTree, b: Tensor, h: Tensor, g: Tensor, t: Tensor, t_c: Tensor,
                          t_r: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """Level D: (hand vertex, triangle) rows within reach, each with its exact closest point: frame ``b``, group
    ``g``, triangle ``t``, hand vertex ``v`` ``(N,)`` each, closest points ``cp (N, 3)``, the signed side ``(N,)``
    of the vertex against the triangle's plane; from the triangle rows of :func:`_triangle_candidates`."""
    geom, x, ext, params = blk.geom, blk.x, blk.ext, blk.params
    v, idx = nearest.within(t_c, b, h, t_r + blk.upper[g] + blk.slack)
    b, g, t, t_c, t_r = b[idx], g[idx], t[idx], t_c[idx], t_r[idx]
    p = x[b, v]
    # Per hand vertex, only the triangles that can beat its distance to the nearest of their centroids (its own
    # closest triangles, ties included, always pass: their lower bound is at most its distance).
    dense = g * geom.hand_width + geom.hand_local[v]
    dc = (p - t_c).norm(dim=-1)
    keep = dc - t_r <= _group_min(dc, dense, blk.n_g * geom.hand_width)[dense] + params.tie_m
    b, g, t, v, p = b[keep], g[keep], t[keep], v[keep], p[keep]
    tri = ext[b[:, None], geom.faces[t]]
    cp = closest_points(p, tri[:, 0], tri[:, 1], tri[:, 2])
    normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return b, g, t, v, cp, ((p - cp) * normal).sum(-1)


def _group_results(blk: _Block, b: Tensor, g: Tensor, t: Tensor, v: Tensor, cp: Tensor, side: Tensor
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """Per group ``(n_g,)``: distance, inside, its K closest (hand vertex, part vertex) pairs ``(n_g, K, 2)`` and
    their distances ``(n_g, K)``, from the exact rows of :func:`_vertex_triangle_rows`."""
    geom, x, n_g = blk.geom, blk.x, blk.n_g
    dense = g * geom.hand_width + geom.hand_local[v]
    size = n_g * geom.hand_width
    d = (x[b, v] - cp).norm(dim=-1)
    # Per (group, hand vertex): closest distance, its triangle, and the sign at its closest point.
    d_dense = _group_min(d, dense, size)
    tied = d <= d_dense[dense] + blk.params.tie_m
    best = _argmin_by_group(d, dense, size)  # entry of each key's closest triangle
    side_dense = torch.zeros(size, dtype=x.dtype).index_add_(0, dense, torch.where(tied, side, 0.0))
    keys = torch.nonzero(torch.isfinite(d_dense)).flatten()
    d_key, best, side_key = d_dense[keys], best[keys], side_dense[keys]
    g_key = keys // geom.hand_width
    # A vertex's triangle set is complete (so its distance and side are right) when its distance is within the
    # bound every culling level used.
    valid = d_key <= blk.upper[g_key] + blk.slack
    in_key = valid & (d_key <= blk.cutoff) & (side_key < 0)  # beyond the cutoff level A may have left triangles out
    inside_g = torch.zeros(n_g, dtype=torch.bool)
    inside_g[g_key[in_key]] = True
    dist_g = _group_min(torch.where(valid, d_key, torch.inf), g_key, n_g)
    dist_g = torch.where(inside_g, torch.zeros_like(dist_g), dist_g)
    sel = torch.nonzero(valid).flatten()
    pairs, pair_d = _closest_pairs(blk, g_key[sel], d_key[sel], best[sel], b, t, v, cp)
    far = dist_g > blk.cutoff
    dist_g[far] = torch.inf
    pairs[far] = -1
    pair_d[far] = torch.inf
    return dist_g, inside_g, pairs, pair_d


def _closest_pairs(blk: _Block, g_key: Tensor, d_key: Tensor, entry: Tensor, b: Tensor, t: Tensor, v: Tensor,
                   cp: Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
    """The K closest hand vertices of each group ``(n_g, K, 2)`` (hand vertex, the part vertex nearest its
    closest point) and their distances ``(n_g, K)``; from the valid keys' group, distance and best row."""
    n_g, k_pairs, n_v = blk.n_g, blk.params.pairs, blk.x.shape[1]
    pairs = torch.full((n_g, k_pairs, 2), -1, dtype=torch.long)
    pair_d = torch.full((n_g, k_pairs), float("inf"), dtype=blk.x.dtype)
    order, rank = _ranked(g_key, d_key)
    sel, rank = order[rank < k_pairs], rank[rank < k_pairs]
    e = entry[sel]
    corners = blk.geom.faces[t[e]]  # (S, 3)
    corner_d = (blk.ext[b[e][:, None], corners] - cp[e][:, None]).norm(dim=-1)
    corner_d = torch.where(corners < n_v, corner_d, torch.inf)  # a cap's centre is not a vertex of the body
    part_vertex = corners.gather(1, corner_d.argmin(1, keepdim=True))[:, 0]
    gsel = g_key[sel]
    pairs[gsel, rank, 0] = v[e]
    pairs[gsel, rank, 1] = part_vertex
    pair_d[gsel, rank] = d_key[sel]
    # Fewer hand vertices than pairs asked for: repeat the closest.
    for r in range(1, k_pairs):
        missing = (pairs[:, r, 0] < 0) & (pairs[:, 0, 0] >= 0)
        pairs[missing, r] = pairs[missing, 0]
        pair_d[missing, r] = pair_d[missing, 0]
    return pairs, pair_d


def hand_part_distances(
    character: Character | None,
    parts: BodyParts,
    posed: Tensor,
    params: HandDistanceParams | None = None,
    geometry: HandPartGeometry | None = None,
    height: float | None = None,
) -> HandPartDistances:
    """Distances ``(F, 2, P)`` from each hand to each part of the posed body ``posed (F, V, 3)`` (see the module
    doc). ``character`` gives the rest pose and height; without it, give ``height`` (the first frame then lays
    out the chunks). ``geometry``: a :func:`hand_part_geometry` of this body to reuse."""
    params = params or HandDistanceParams()
    if character is not None:
        rest, height = character.vertices, height or character.height
    else:
        if height is None:
            raise ValueError("give the character or its height")
        rest = posed[0] if len(posed) else torch.zeros(parts.weights.shape[0], 3)
    geom = geometry or hand_part_geometry(parts, rest, height, params)
    s = height / REFERENCE_HEIGHT_M
    cutoff, slack = params.max_distance_m * s, params.slack_m * s
    f_n, n_h, n_p, k = posed.shape[0], len(geom.hands), len(geom.parts), params.pairs
    dist = torch.full((f_n, n_h, n_p), float("inf"), dtype=torch.float64)
    inside = torch.zeros(f_n, n_h, n_p, dtype=torch.bool)
    pairs = torch.full((f_n, n_h, n_p, k, 2), -1, dtype=torch.long)
    pair_d = torch.full((f_n, n_h, n_p, k), float("inf"), dtype=torch.float64)
    with torch.no_grad():
        for s0 in range(0, f_n, params.frames_per_block):
            s1 = min(f_n, s0 + params.frames_per_block)
            x = posed[s0:s1].detach().to(torch.float64)
            dist[s0:s1], inside[s0:s1], pairs[s0:s1], pair_d[s0:s1] = _block_distances(geom, x, cutoff, slack, params)
    return HandPartDistances(geom.hands, geom.parts, dist, inside, pairs, pair_d, geom.measured.clone(), cutoff)


__all__ = [
    "HandDistanceParams",
    "HandPartDistances",
    "HandPartGeometry",
    "hand_part_distances",
    "hand_part_geometry",
]
