"""Distance from each hand to each other body part's surface, 0 when inside (ACCEPTANCE.md "Hand self-contact").

Parts are the six clusters of :data:`retarget_core.body_parts.CLUSTERS` (head, torso, each arm, each leg): the
triangles whose dominant segment is in the cluster, closed by a fan over every open boundary loop
(:func:`~retarget_core.energy.mesh_distance.cap_boundary_loops`), so every part is a closed volume. Hand vertices
are those whose dominant segment is a hand (fingers included). Per frame and (hand, part):

    d = 0                                  when a hand vertex lies inside the part's closed volume,
    d = min over hand vertices p of dist(p, part surface)   otherwise,

exact (point-triangle distances) up to ``max_distance``, ``inf`` beyond it. A hand's own arm is not measured
(``inf``): the hand is attached to it.

How: a compiled walk per frame (:mod:`retarget_core.contacts.hand_distance_kernel`) over spheres measured on the
posed frame around chunks of at most 32 hand vertices and chunks of at most 32 triangles of one part (grouped once
by rest-pose voxels), nearest pairs of chunks first, pruned by each vertex's and the group's best distance so far;
exact closest points (Ericson, Real-Time Collision Detection 5.1.5) on what is left. A vertex is inside when
``(p - q) . n`` summed over the triangles tied at its closest point ``q`` is negative (the pseudonormal test: exact
on faces and edges, equal weights instead of angle weights at vertices). The slack (5 mm at 1.80 m, the median
hand edge) makes the test reach the vertices of a hand triangle that crosses the surface, so a hand partly sunk
into the body reads 0, and a fully sunk one reads 0 too (its nearest vertex is inside).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, HAND_SEGMENTS, BodyParts
from retarget_core.character import Character
from retarget_core.contacts.hand_distance_kernel import block_distances
from retarget_core.energy.mesh_distance import cap_boundary_loops
from retarget_core.energy.sdf import vertex_clusters
from retarget_core.geometry.bvh_kernels import run_in_blocks

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
    # Rest-pose voxel edge of the hand and triangle chunks in median edges of the hands' and the parts' triangles
    # (efficiency only, results do not depend on it): chunks of about as many members on a fine mesh as on a coarse
    # one (on a MakeHuman body about 3 and 4 cm; a finer mesh's larger spheres pruned nothing near a contact: with
    # 3 and 6 cm the large character's distances took 2.2 x as long, docs/results.md).
    hand_chunk_edges: float = 6.0
    triangle_chunk_edges: float = 4.0
    chunk_members: int = 32
    # Triangles within this of a vertex's closest distance share its closest point (a face, edge or vertex).
    tie_m: float = 1e-7
    # Closest (hand vertex, part vertex) pairs kept per (frame, hand, part).
    pairs: int = 3
    frames_per_block: int = 16
    # Frames per thread at least (the walks release the GIL).
    frames_per_thread: int = 8


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
    hand_local: ``(V,)`` each hand vertex's index within its hand (-1 elsewhere).
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
    hand_local: Tensor
    hand_table: np.ndarray = field(init=False)  # (2, N) each hand's vertices, -1 padded
    part_chunks: np.ndarray = field(init=False)  # (P, M) each part's triangle chunks, -1 padded

    def __post_init__(self) -> None:
        self.hand_table = _padded([v.numpy() for v in self.hand_vertices]).numpy()
        chunk_part = self.tri_chunk_part.numpy()
        self.part_chunks = _padded([np.nonzero(chunk_part == p)[0] for p in range(len(self.parts))]).numpy()


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


def median_edge(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The median edge length of the triangles ``faces (T, 3)`` over ``vertices (V, 3)`` (0 without any)."""
    if len(faces) == 0:
        return 0.0
    corners = vertices[faces]
    return float(np.median(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1)))


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
    on_hand = np.isin(faces, hv.numpy()).all(axis=1)  # (T,) the hands' own triangles
    if len(hv):
        hand_edge = median_edge(v_np, faces[on_hand]) or 0.005 * s
        members, chunk_hand = _chunks(vertices[hv], hl, params.hand_chunk_edges * hand_edge, params.chunk_members)
        hand_chunks = torch.where(members >= 0, hv[members.clamp_min(0)], members)
    else:
        hand_chunks, chunk_hand = torch.full((0, 1), -1, dtype=torch.long), torch.zeros(0, dtype=torch.long)
    chunks_of_hand = _padded([np.nonzero(chunk_hand.numpy() == i)[0] for i in range(len(hands))])
    # Triangle chunks by rest centroid.
    centroid = torch.from_numpy(ext[faces_t.numpy()].mean(1))
    part_edge = median_edge(v_np, faces[~on_hand]) or 0.01 * s
    tri_chunks, tri_chunk_part = _chunks(centroid, face_part, params.triangle_chunk_edges * part_edge,
                                         params.chunk_members)  # fmt: skip
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
        hand_chunks, chunk_hand, chunks_of_hand, tri_chunks, tri_chunk_part, tri_chunk_vertices, measured, hand_local,
    )  # fmt: skip


def _block_distances(geom: HandPartGeometry, x: Tensor, cutoffs: Tensor, slack: float, params: HandDistanceParams
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """One block of frames ``x (B, V, 3)`` (float64) measured up to ``cutoffs (B, 2, P)`` (0: not measured):
    distance, inside ``(B, 2, P)``, pairs ``(B, 2, P, K, 2)``, pair distances ``(B, 2, P, K)``."""
    bsz, shape = x.shape[0], tuple(cutoffs.shape)
    centres = torch.zeros(bsz, len(geom.ring_count), 3, dtype=x.dtype).index_add_(1, geom.ring_cap, x[:, geom.ring_vertex])
    ext = torch.cat([x, centres / geom.ring_count.clamp_min(1).to(x.dtype)[None, :, None]], dim=1).numpy()
    reach = cutoffs.to(torch.float64).numpy()
    dist = np.full(shape, np.inf)
    inside = np.zeros(shape, dtype=np.bool_)
    pairs = np.full((*shape, params.pairs, 2), -1, dtype=np.int64)
    pair_d = np.full((*shape, params.pairs), np.inf)
    tables = (geom.faces.numpy(), geom.tri_chunks.numpy(), geom.tri_chunk_vertices.numpy(), geom.part_chunks,
              geom.hand_chunks.numpy(), geom.chunks_of_hand.numpy(), geom.hand_table, geom.hand_local.numpy())  # fmt: skip

    def walk(s: slice) -> None:
        block_distances(ext[s], x.shape[1], *tables, reach[s], slack, params.tie_m, dist[s], inside[s], pairs[s],
                        pair_d[s])  # fmt: skip

    run_in_blocks(walk, bsz, params.frames_per_thread)
    return torch.from_numpy(dist), torch.from_numpy(inside), torch.from_numpy(pairs), torch.from_numpy(pair_d)


def hand_part_distances(
    character: Character | None,
    parts: BodyParts,
    posed: Tensor,
    params: HandDistanceParams | None = None,
    geometry: HandPartGeometry | None = None,
    height: float | None = None,
    cutoffs: Tensor | None = None,
) -> HandPartDistances:
    """Distances ``(F, 2, P)`` from each hand to each part of the posed body ``posed (F, V, 3)`` (see the module
    doc). ``character`` gives the rest pose and height; without it, give ``height`` (the first frame then lays
    out the chunks). ``geometry``: a :func:`hand_part_geometry` of this body to reuse. ``cutoffs (F, 2, P)``:
    each group's own cutoff (m on the body; 0: not measured); default ``params.max_distance_m`` (scaled). Only
    the pairs :attr:`HandPartGeometry.measured` names are measured."""
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
            given = torch.full((s1 - s0, n_h, n_p), cutoff) if cutoffs is None else cutoffs[s0:s1]
            reach = given * geom.measured[None]  # (B, 2, P)
            dist[s0:s1], inside[s0:s1], pairs[s0:s1], pair_d[s0:s1] = _block_distances(geom, x, reach, slack, params)
    return HandPartDistances(geom.hands, geom.parts, dist, inside, pairs, pair_d, geom.measured.clone(), cutoff)


__all__ = [
    "HandDistanceParams",
    "HandPartDistances",
    "HandPartGeometry",
    "hand_part_distances",
    "hand_part_geometry",
]
