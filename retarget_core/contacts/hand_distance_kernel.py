"""Compiled hand-to-part distances of one frame (:mod:`retarget_core.contacts.hand_distance` lays out the data).

Per (hand, part) group, with bounding spheres measured on the posed frame (so skinning cannot invalidate them):

1. the part's triangle chunks whose sphere comes within ``cutoff + slack`` of the hand's sphere, then the (hand
   chunk, triangle chunk) pairs within it; one exact distance of the nearest pair bounds the group's ``U``, so
   only the pairs within that bound plus the slack are sorted and walked, nearest first (the walk would stop
   before the others: the same pairs in the same order, without sorting thousands of far ones);
2. per hand vertex, exact point-triangle distances (Ericson 5.1.5) of the triangles whose sphere can still beat
   both that vertex's best and the group's best ``U`` plus the slack (``U`` only falls, so nothing skipped could
   have mattered): every vertex within ``U + slack`` of the part ends with its exact distance;
3. per such vertex, the pseudonormal side summed over the triangles tied at its closest distance (inside when
   negative), and its closest triangle's nearest body vertex.

A group is inside when a vertex within the slack of the closest one is inside; its K closest vertices make the
pairs (the closest repeated when fewer lie within the slack). Compiled with numba (cached on disk; it releases the GIL).
"""

from __future__ import annotations

import math

import numpy as np

from retarget_core.geometry.bvh_kernels import _compiled, closest_point


@_compiled
def _spheres(ext: np.ndarray, members: np.ndarray, rows: np.ndarray, centre: np.ndarray, radius: np.ndarray) -> None:
    """Centre ``(C, 3)`` (the members' mean) and radius ``(C,)`` of the groups ``rows`` (-1 ends the list) of
    ``members (C, K)`` (-1 padded, indices into ``ext (V, 3)``) into ``centre``, ``radius``."""
    for c in rows:
        if c < 0:
            break
        n, sx, sy, sz = 0, 0.0, 0.0, 0.0
        for k in range(members.shape[1]):
            v = members[c, k]
            if v < 0:
                break
            n += 1
            sx, sy, sz = sx + ext[v, 0], sy + ext[v, 1], sz + ext[v, 2]
        n = max(n, 1)
        cx, cy, cz = sx / n, sy / n, sz / n
        r = 0.0
        for k in range(members.shape[1]):
            v = members[c, k]
            if v < 0:
                break
            r = max(r, math.sqrt((ext[v, 0] - cx) ** 2 + (ext[v, 1] - cy) ** 2 + (ext[v, 2] - cz) ** 2))
        centre[c, 0], centre[c, 1], centre[c, 2], radius[c] = cx, cy, cz, r


@_compiled
def _gap(a: np.ndarray, ra: float, b: np.ndarray, rb: float) -> float:
    """Lower bound on the distance between two spheres (negative when they overlap)."""
    return math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2) - ra - rb


@_compiled
def _chunk_pairs(h_chunks: np.ndarray, part_chunks: np.ndarray, hand_c: np.ndarray, hand_r: float,
                 hc_c: np.ndarray, hc_r: np.ndarray, tc_c: np.ndarray, tc_r: np.ndarray, reach: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(hand chunk, triangle chunk) pairs of one group within ``reach``, in no order: hand chunk ``(N,)``,
    triangle chunk ``(N,)``, lower bound ``(N,)``; the triangle chunks first against the whole hand's sphere
    ``hand_c (3,)``, ``hand_r``."""
    near = np.empty(len(part_chunks), dtype=np.int64)
    n_t = 0
    for b in range(len(part_chunks)):
        q = part_chunks[b]
        if q < 0:
            break
        if _gap(hand_c, hand_r, tc_c[q], tc_r[q]) <= reach:
            near[n_t] = q
            n_t += 1
    n_h = 0
    while n_h < len(h_chunks) and h_chunks[n_h] >= 0:
        n_h += 1
    hj = np.empty(n_h * n_t, dtype=np.int64)
    tq = np.empty(n_h * n_t, dtype=np.int64)
    lb = np.empty(n_h * n_t)
    n = 0
    for a in range(n_h):
        j = h_chunks[a]
        for b in range(n_t):
            q = near[b]
            gap = _gap(hc_c[j], hc_r[j], tc_c[q], tc_r[q])
            if gap <= reach:
                hj[n], tq[n], lb[n] = j, q, gap
                n += 1
    return hj[:n], tq[:n], lb[:n]


@_compiled
def _pair_upper(ext: np.ndarray, faces: np.ndarray, hand_chunks: np.ndarray, tri_chunks: np.ndarray, j: int,
                q: int, centre: np.ndarray) -> float:  # fmt: skip
    """An upper bound on a group's distance: the exact distance from the vertex of hand chunk ``j`` nearest
    ``centre (3,)`` (triangle chunk ``q``'s) to the nearest of that chunk's triangles."""
    pick, near = -1, np.inf
    for k in range(hand_chunks.shape[1]):
        v = hand_chunks[j, k]
        if v < 0:
            break
        d = (ext[v, 0] - centre[0]) ** 2 + (ext[v, 1] - centre[1]) ** 2 + (ext[v, 2] - centre[2]) ** 2
        if d < near:
            pick, near = v, d
    px, py, pz = ext[pick, 0], ext[pick, 1], ext[pick, 2]
    upper = np.inf
    for m in range(tri_chunks.shape[1]):
        t = tri_chunks[q, m]
        if t < 0:
            break
        tri = faces[t]
        qx, qy, qz = closest_point(px, py, pz, ext[tri[0]], ext[tri[1]], ext[tri[2]])
        upper = min(upper, math.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2))
    return upper


@_compiled
def _nearest_first(hj: np.ndarray, tq: np.ndarray, lb: np.ndarray, within: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The pairs ``hj, tq, lb (N,)`` whose lower bound is within ``within``, nearest first (a stable sort: the
    same order as sorting them all and cutting the list there)."""
    keep = np.nonzero(lb <= within)[0]
    order = keep[np.argsort(lb[keep], kind="mergesort")]
    return hj[order], tq[order], lb[order]


@_compiled
def _triangle_spheres(ext: np.ndarray, faces: np.ndarray, tri_chunks: np.ndarray, q: int, tri_sph: np.ndarray,
                      ready: np.ndarray) -> None:
    """Centroid and radius of the posed triangles of chunk ``q`` into ``tri_sph[q] (K, 4)``, once a frame
    (``ready (Q,)``)."""
    if ready[q]:
        return
    for m in range(tri_chunks.shape[1]):
        t = tri_chunks[q, m]
        if t < 0:
            break
        tri = faces[t]
        cx = (ext[tri[0], 0] + ext[tri[1], 0] + ext[tri[2], 0]) / 3.0
        cy = (ext[tri[0], 1] + ext[tri[1], 1] + ext[tri[2], 1]) / 3.0
        cz = (ext[tri[0], 2] + ext[tri[1], 2] + ext[tri[2], 2]) / 3.0
        r = 0.0
        for k in range(3):
            r = max(r, (ext[tri[k], 0] - cx) ** 2 + (ext[tri[k], 1] - cy) ** 2 + (ext[tri[k], 2] - cz) ** 2)
        tri_sph[q, m, 0], tri_sph[q, m, 1], tri_sph[q, m, 2], tri_sph[q, m, 3] = cx, cy, cz, math.sqrt(r)
    ready[q] = True


@_compiled
def _best_distances(ext: np.ndarray, faces: np.ndarray, hand_chunks: np.ndarray, tri_chunks: np.ndarray,
                    hj: np.ndarray, tq: np.ndarray, lb: np.ndarray, tc_c: np.ndarray, tc_r: np.ndarray,
                    hand_local: np.ndarray, cutoff: float, slack: float, tie: float, tri_sph: np.ndarray,
                    ready: np.ndarray, best: np.ndarray) -> float:
    """Step 2: each hand vertex's distance to the part into ``best`` (by hand-local index; exact where it is
    within the returned group minimum ``U`` plus the slack); returns ``U``."""
    upper = np.inf
    for i in range(len(hj)):
        reach = min(upper, cutoff) + slack
        if lb[i] > reach:
            break  # the pairs come nearest first
        q = tq[i]
        for k in range(hand_chunks.shape[1]):
            v = hand_chunks[hj[i], k]
            if v < 0:
                break
            loc = hand_local[v]
            px, py, pz = ext[v, 0], ext[v, 1], ext[v, 2]
            bound = min(best[loc] + tie, reach)
            if math.sqrt((px - tc_c[q, 0]) ** 2 + (py - tc_c[q, 1]) ** 2 + (pz - tc_c[q, 2]) ** 2) - tc_r[q] > bound:
                continue
            _triangle_spheres(ext, faces, tri_chunks, q, tri_sph, ready)
            for m in range(tri_chunks.shape[1]):
                t = tri_chunks[q, m]
                if t < 0:
                    break
                sph = tri_sph[q, m]
                if math.sqrt((px - sph[0]) ** 2 + (py - sph[1]) ** 2 + (pz - sph[2]) ** 2) - sph[3] > bound:
                    continue
                tri = faces[t]
                qx, qy, qz = closest_point(px, py, pz, ext[tri[0]], ext[tri[1]], ext[tri[2]])
                d = math.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)
                if d < best[loc]:
                    best[loc] = d
                    upper = min(upper, d)
                    reach = min(upper, cutoff) + slack
                    bound = min(d + tie, reach)
    return upper


@_compiled
def _sides(ext: np.ndarray, faces: np.ndarray, hand_chunks: np.ndarray, tri_chunks: np.ndarray, hj: np.ndarray,
           tq: np.ndarray, lb: np.ndarray, tc_c: np.ndarray, tc_r: np.ndarray, hand_local: np.ndarray,
           valid_reach: float, tie: float, tri_sph: np.ndarray, ready: np.ndarray, best: np.ndarray,
           side: np.ndarray, closest_face: np.ndarray, closest: np.ndarray) -> None:  # fmt: skip
    """Step 3, for the vertices with ``best <= valid_reach``: the side summed over their tied triangles into
    ``side``, their closest triangle (the lowest index of those tied) into ``closest_face`` and its closest point
    into ``closest (N, 3)``."""
    # The chunk and triangle bounds are written out as in step 2: as shared helpers the walk took 2.6 x longer.
    for i in range(len(hj)):
        if lb[i] > valid_reach:
            break
        q = tq[i]
        for k in range(hand_chunks.shape[1]):
            v = hand_chunks[hj[i], k]
            if v < 0:
                break
            loc = hand_local[v]
            if best[loc] > valid_reach:
                continue
            px, py, pz = ext[v, 0], ext[v, 1], ext[v, 2]
            bound = best[loc] + tie
            if math.sqrt((px - tc_c[q, 0]) ** 2 + (py - tc_c[q, 1]) ** 2 + (pz - tc_c[q, 2]) ** 2) - tc_r[q] > bound:
                continue
            _triangle_spheres(ext, faces, tri_chunks, q, tri_sph, ready)
            for m in range(tri_chunks.shape[1]):
                t = tri_chunks[q, m]
                if t < 0:
                    break
                sph = tri_sph[q, m]
                if math.sqrt((px - sph[0]) ** 2 + (py - sph[1]) ** 2 + (pz - sph[2]) ** 2) - sph[3] > bound:
                    continue
                tri = faces[t]
                a, b, c = ext[tri[0]], ext[tri[1]], ext[tri[2]]
                qx, qy, qz = closest_point(px, py, pz, a, b, c)
                d = math.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)
                if d > bound:
                    continue
                nx = (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1])
                ny = (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2])
                nz = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
                norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
                side[loc] += ((px - qx) * nx + (py - qy) * ny + (pz - qz) * nz) / norm
                if d <= best[loc] and (closest_face[loc] < 0 or t < closest_face[loc]):  # ties: the lowest index,
                    closest_face[loc] = t  # whatever the order the chunks are walked in
                    closest[loc, 0], closest[loc, 1], closest[loc, 2] = qx, qy, qz


@_compiled
def _part_vertex(ext: np.ndarray, tri: np.ndarray, qx: float, qy: float, qz: float, n_v: int) -> int:
    """The corner of ``tri (3,)`` nearest the point ``q`` that is a body vertex (not a cap's centre)."""
    best, out = np.inf, -1
    for k in range(3):
        w = tri[k]
        if w >= n_v:
            continue
        d = (ext[w, 0] - qx) ** 2 + (ext[w, 1] - qy) ** 2 + (ext[w, 2] - qz) ** 2
        if d < best:
            best, out = d, w
    return out


@_compiled
def _group_result(ext: np.ndarray, faces: np.ndarray, vertices: np.ndarray, hand_local: np.ndarray, cutoff: float,
                  reach: float, best: np.ndarray, side: np.ndarray, closest_face: np.ndarray, closest: np.ndarray,
                  n_v: int, pairs: np.ndarray, pair_d: np.ndarray) -> tuple[float, bool]:
    """Distance and inside of a group from its vertices ``vertices (N,)`` (body indices; those within ``reach``
    count), its K closest (hand vertex, part vertex) into ``pairs (K, 2)`` and their distances into ``pair_d (K,)``."""
    inside, upper = False, np.inf
    for v in vertices:
        loc = hand_local[v]
        upper = min(upper, best[loc])
        if best[loc] <= min(cutoff, reach) and side[loc] < 0:
            inside = True
    taken = 0
    last_d, last_loc = -1.0, -1
    for r in range(pairs.shape[0]):
        pick, pick_d, pick_loc = -1, np.inf, -1
        for v in vertices:  # the next closest vertex within reach, lower hand-local index first on ties
            loc = hand_local[v]
            d = best[loc]
            if d > reach or d < last_d or (d == last_d and loc <= last_loc):
                continue
            if d < pick_d or (d == pick_d and loc < pick_loc):
                pick, pick_d, pick_loc = v, d, loc
        if pick < 0:
            break
        f = closest_face[pick_loc]
        pairs[r, 0] = pick
        pairs[r, 1] = _part_vertex(ext, faces[f], closest[pick_loc, 0], closest[pick_loc, 1], closest[pick_loc, 2], n_v)
        pair_d[r] = pick_d
        last_d, last_loc = pick_d, pick_loc
        taken += 1
    for r in range(taken, pairs.shape[0]):  # fewer vertices than pairs: repeat the closest
        pairs[r, 0], pairs[r, 1], pair_d[r] = pairs[0, 0], pairs[0, 1], pair_d[0]
    return (0.0 if inside else upper), inside


@_compiled
def _frame_distances(ext: np.ndarray, n_v: int, faces: np.ndarray, tri_chunks: np.ndarray,
                    tri_chunk_vertices: np.ndarray, part_chunks: np.ndarray, hand_chunks: np.ndarray,
                    chunks_of_hand: np.ndarray, hand_vertices: np.ndarray, hand_local: np.ndarray,
                    cutoffs: np.ndarray, slack: float, tie: float, dist: np.ndarray, inside: np.ndarray,
                    pairs: np.ndarray, pair_d: np.ndarray) -> None:  # fmt: skip
    """One posed frame ``ext (V + caps, 3)`` (``n_v`` body vertices, then the caps' centres): per (hand, part)
    group measured up to ``cutoffs (2, P)`` (0: not measured), into ``dist, inside (2, P)``, ``pairs (2, P, K,
    2)`` and ``pair_d (2, P, K)`` (filled with inf, False and -1 before the call). ``hand_vertices (2, N)`` and
    ``part_chunks (P, M)`` -1 padded."""
    tc_c = np.empty((tri_chunks.shape[0], 3))
    tc_r = np.empty(tri_chunks.shape[0])
    for p in range(cutoffs.shape[1]):
        if (cutoffs[:, p] > 0).any():  # only the chunks of the parts measured
            _spheres(ext, tri_chunk_vertices, part_chunks[p], tc_c, tc_r)
    hc_c = np.empty((hand_chunks.shape[0], 3))
    hc_r = np.empty(hand_chunks.shape[0])
    _spheres(ext, hand_chunks, np.arange(hand_chunks.shape[0]), hc_c, hc_r)
    width = hand_vertices.shape[1]
    tri_sph = np.empty((tri_chunks.shape[0], tri_chunks.shape[1], 4))
    ready = np.zeros(tri_chunks.shape[0], dtype=np.bool_)
    hand_c = np.empty((hand_vertices.shape[0], 3))
    hand_r = np.empty(hand_vertices.shape[0])
    _spheres(ext, hand_vertices, np.arange(hand_vertices.shape[0]), hand_c, hand_r)
    best, side = np.empty(width), np.empty(width)
    closest_face, closest = np.empty(width, dtype=np.int64), np.empty((width, 3))
    for h in range(cutoffs.shape[0]):
        verts = hand_vertices[h][hand_vertices[h] >= 0]
        for p in range(cutoffs.shape[1]):
            cutoff = cutoffs[h, p]
            if cutoff <= 0:
                continue
            hj, tq, lb = _chunk_pairs(chunks_of_hand[h], part_chunks[p], hand_c[h], hand_r[h], hc_c, hc_r, tc_c, tc_r,
                                      cutoff + slack)  # fmt: skip
            if len(hj) == 0:
                continue
            first = np.argmin(lb)  # its exact distance bounds the group's: pairs farther than it plus the slack
            near = _pair_upper(ext, faces, hand_chunks, tri_chunks, hj[first], tq[first], tc_c[tq[first]])
            hj, tq, lb = _nearest_first(hj, tq, lb, min(near, cutoff) + slack)  # are never walked, nor sorted
            best[:] = np.inf
            side[:] = 0.0
            closest_face[:] = -1
            upper = _best_distances(ext, faces, hand_chunks, tri_chunks, hj, tq, lb, tc_c, tc_r, hand_local, cutoff,
                                    slack, tie, tri_sph, ready, best)  # fmt: skip
            if upper > cutoff:
                continue
            _sides(ext, faces, hand_chunks, tri_chunks, hj, tq, lb, tc_c, tc_r, hand_local, upper + slack, tie, tri_sph,
                   ready, best, side, closest_face, closest)  # fmt: skip
            dist[h, p], inside[h, p] = _group_result(ext, faces, verts, hand_local, cutoff, upper + slack, best, side,
                                                     closest_face, closest, n_v, pairs[h, p], pair_d[h, p])  # fmt: skip


@_compiled
def block_distances(ext: np.ndarray, n_v: int, faces: np.ndarray, tri_chunks: np.ndarray,
                    tri_chunk_vertices: np.ndarray, part_chunks: np.ndarray, hand_chunks: np.ndarray,
                    chunks_of_hand: np.ndarray, hand_vertices: np.ndarray, hand_local: np.ndarray,
                    cutoffs: np.ndarray, slack: float, tie: float, dist: np.ndarray, inside: np.ndarray,
                    pairs: np.ndarray, pair_d: np.ndarray) -> None:  # fmt: skip
    """:func:`_frame_distances` of every frame of ``ext (B, V + caps, 3)`` with ``cutoffs (B, 2, P)`` into
    ``dist, inside (B, 2, P)``, ``pairs (B, 2, P, K, 2)``, ``pair_d (B, 2, P, K)``."""
    for b in range(ext.shape[0]):
        _frame_distances(ext[b], n_v, faces, tri_chunks, tri_chunk_vertices, part_chunks, hand_chunks, chunks_of_hand,
                         hand_vertices, hand_local, cutoffs[b], slack, tie, dist[b], inside[b], pairs[b],
                         pair_d[b])  # fmt: skip


__all__ = ["block_distances"]
