"""Signed distances from grid points to triangle meshes (numpy, scipy): the precomputation behind the SDF grids.

- unsigned distance: exact point-to-triangle distance to the candidate triangles found by a KD-tree over
  points sampled on the surface (scipy cKDTree);
- sign: parity of ray crossings along the three grid axes, by majority, so a single hole or a ray grazing an
  edge does not flip a voxel;
- :func:`cap_boundary_loops` closes the holes of a body part cut out of a closed mesh (a fan per boundary loop),
  so every part is a closed volume.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def closest_point_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance ``(...)`` from points ``p (..., 3)`` to triangles ``(a, b, c)`` each ``(..., 3)``."""
    return np.linalg.norm(p - closest_point(p, a, b, c), axis=-1)


def closest_point(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points ``(..., 3)`` to ``p (..., 3)`` on triangles ``(a, b, c)`` each ``(..., 3)`` (Ericson,
    Real-Time Collision Detection 5.1.5, vectorised; degenerate triangles are handled through their edges)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("...i,...i->...", ab, ap)
    d2 = np.einsum("...i,...i->...", ac, ap)
    bp = p - b
    d3 = np.einsum("...i,...i->...", ab, bp)
    d4 = np.einsum("...i,...i->...", ac, bp)
    cp = p - c
    d5 = np.einsum("...i,...i->...", ab, cp)
    d6 = np.einsum("...i,...i->...", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        # Interior by default.
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        q = a + ab * v[..., None] + ac * w[..., None]
        # Edge regions.
        t_ab = np.clip(d1 / np.where(d1 - d3 != 0, d1 - d3, 1.0), 0.0, 1.0)
        t_ac = np.clip(d2 / np.where(d2 - d6 != 0, d2 - d6, 1.0), 0.0, 1.0)
        den_bc = (d4 - d3) + (d5 - d6)
        t_bc = np.clip((d4 - d3) / np.where(den_bc != 0, den_bc, 1.0), 0.0, 1.0)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    q = np.where(on_bc[..., None], b + (c - b) * t_bc[..., None], q)
    q = np.where(on_ac[..., None], a + ac * t_ac[..., None], q)
    q = np.where(on_ab[..., None], a + ab * t_ab[..., None], q)
    # Vertex regions.
    q = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, q)
    # Degenerate triangles (no area): the nearest point of the three edges.
    degenerate = ~np.isfinite(q).all(-1) | (np.abs(denom) < 1e-30)
    if np.any(degenerate):
        q = np.where(degenerate[..., None], _edge_point(p, a, b, c), q)
    return q


def _segment_point(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.einsum("...i,...i->...", p - a, ab) / np.maximum(np.einsum("...i,...i->...", ab, ab), 1e-30)
    return a + ab * np.clip(t, 0.0, 1.0)[..., None]


def _edge_point(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    cands = np.stack([_segment_point(p, a, b), _segment_point(p, b, c), _segment_point(p, a, c)])
    k = np.argmin(np.linalg.norm(cands - p, axis=-1), axis=0)
    return np.take_along_axis(cands, k[None, ..., None], axis=0)[0]


def sample_surface(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 3)`` on a barycentric lattice of every triangle (corners included) at most about
    ``spacing`` apart, and the triangle ``(N,)`` each point lies on."""
    tri = vertices[faces]  # (T, 3, 3)
    edge = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=-1).max(axis=1)
    n_sub = np.clip(np.ceil(edge / max(spacing, 1e-9)), 1, 32).astype(np.int64)
    points, owners = [], []
    for n in np.unique(n_sub):
        sel = np.nonzero(n_sub == n)[0]
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j) <= n
        bary = np.stack([i[keep], j[keep]], axis=1) / float(n)  # (L, 2)
        t = tri[sel]
        pts = t[:, None, 0] + bary[None, :, 0:1] * (t[:, None, 1] - t[:, None, 0]) + bary[None, :, 1:2] * (t[:, None, 2] - t[:, None, 0])
        points.append(pts.reshape(-1, 3))
        owners.append(np.repeat(sel, len(bary)))
    return np.concatenate(points), np.concatenate(owners)


class MeshDistance:
    """Unsigned distance to a triangle mesh: KD-tree over surface samples, then exact distances to the
    triangles of the ``k`` nearest samples (exact whenever the closest triangle owns one of them; otherwise
    off by at most about the sample spacing)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, spacing: float, k: int = 6) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        samples, self.owner = sample_surface(self.vertices, self.faces, spacing)
        self.tree = cKDTree(samples)
        self.k = k

    def query(self, points: np.ndarray, upper: float = np.inf, chunk: int = 65536) -> np.ndarray:
        """Distances ``(P,)`` from ``points (P, 3)`` to the surface; ``inf`` where no surface sample lies within
        ``upper`` (then the distance is more than about ``upper`` minus the sample spacing)."""
        return np.linalg.norm(points - self.closest(points, upper, chunk), axis=-1)

    def closest(self, points: np.ndarray, upper: float = np.inf, chunk: int = 65536) -> np.ndarray:
        """Closest surface points ``(P, 3)``; ``inf`` rows where no sample lies within ``upper``."""
        out = np.full((len(points), 3), np.inf)
        k = min(self.k, self.tree.n)
        for s in range(0, len(points), chunk):
            p = points[s : s + chunk]
            dist, idx = self.tree.query(p, k=k, distance_upper_bound=upper, workers=-1)
            dist, idx = dist.reshape(len(p), k), idx.reshape(len(p), k)
            found = np.isfinite(dist[:, 0])
            if not np.any(found):
                continue
            idx = np.where(np.isfinite(dist), idx, idx[:, :1])[found]
            tri = self.vertices[self.faces[self.owner[idx]]]  # (P', k, 3, 3)
            pf = p[found]
            q = closest_point(pf[:, None, :], tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])  # (P', k, 3)
            best = np.argmin(np.linalg.norm(q - pf[:, None, :], axis=-1), axis=1)
            block = out[s : s + chunk]
            block[found] = q[np.arange(len(pf)), best]
        return out


def signed_distance_grid(
    origin: np.ndarray, voxel: float, shape: tuple[int, int, int], distance: MeshDistance, band_voxels: float = 3.0
) -> np.ndarray:
    """Signed distance ``shape`` (indexed x, y, z; negative inside) at grid points ``origin + i * voxel`` to the
    closed mesh of ``distance``. Exact (see :class:`MeshDistance`) within ``band_voxels`` of the surface;
    farther points use the closest surface point of their nearest band point (Euclidean distance transform),
    an upper bound that is exact unless the two points' closest surface points differ (medial regions)."""
    from scipy.ndimage import distance_transform_edt

    axes = [origin[a] + np.arange(shape[a]) * voxel for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    cp = distance.closest(pts, upper=band_voxels * voxel)
    band = np.isfinite(cp[:, 0])
    if not np.any(band):
        cp = distance.closest(pts)
    elif not np.all(band):
        # Far points take the closest surface point of their nearest band point (closest-point propagation).
        _, nearest = distance_transform_edt(~band.reshape(shape), return_indices=True)
        flat = np.ravel_multi_index(tuple(nearest), shape).reshape(-1)
        cp = np.where(band[:, None], cp, cp[flat])
    d = np.linalg.norm(pts - cp, axis=-1).reshape(shape)
    inside = inside_grid(origin, voxel, shape, distance.vertices, distance.faces)
    return np.where(inside, -d, d)


def _parity_along(axis: int, origin: np.ndarray, voxel: float, shape: tuple[int, int, int], tri: np.ndarray) -> np.ndarray:
    """Per grid point ``shape``: odd number of surface crossings on the ray from -infinity along ``axis``."""
    u_ax, v_ax = [a for a in range(3) if a != axis]
    nu, nv, nw = shape[u_ax], shape[v_ax], shape[axis]
    # A tiny, irrational offset keeps rays off mesh edges and vertices that lie exactly on grid lines.
    eps_u, eps_v = 1.1e-5 * np.sqrt(2.0) * voxel, 1.3e-5 * np.sqrt(3.0) * voxel
    ou, ov, ow = origin[u_ax] + eps_u, origin[v_ax] + eps_v, origin[axis]
    tu, tv, tw = tri[:, :, u_ax], tri[:, :, v_ax], tri[:, :, axis]
    iu0 = np.clip(np.ceil((tu.min(1) - ou) / voxel), 0, nu).astype(np.int64)
    iu1 = np.clip(np.floor((tu.max(1) - ou) / voxel), -1, nu - 1).astype(np.int64)
    iv0 = np.clip(np.ceil((tv.min(1) - ov) / voxel), 0, nv).astype(np.int64)
    iv1 = np.clip(np.floor((tv.max(1) - ov) / voxel), -1, nv - 1).astype(np.int64)
    cu, cv = np.maximum(iu1 - iu0 + 1, 0), np.maximum(iv1 - iv0 + 1, 0)
    counts = cu * cv
    hist = np.zeros((nu, nv, nw + 1), dtype=np.int32)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(shape, dtype=bool)
    t_idx = np.repeat(np.arange(len(tri)), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    iu = iu0[t_idx] + local // cv[t_idx]
    iv = iv0[t_idx] + local % cv[t_idx]
    pu, pv = ou + iu * voxel, ov + iv * voxel
    au, av = tu[t_idx], tv[t_idx]
    # 2D barycentric coordinates of the ray in the projected triangle.
    e1u, e1v = au[:, 1] - au[:, 0], av[:, 1] - av[:, 0]
    e2u, e2v = au[:, 2] - au[:, 0], av[:, 2] - av[:, 0]
    det = e1u * e2v - e2u * e1v
    ok = np.abs(det) > 1e-20
    qu, qv = pu - au[:, 0], pv - av[:, 0]
    safe = np.where(ok, det, 1.0)
    b1 = (qu * e2v - e2u * qv) / safe
    b2 = (e1u * qv - qu * e1v) / safe
    hit = ok & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1)
    w_tri = tw[t_idx]
    w = w_tri[:, 0] + b1 * (w_tri[:, 1] - w_tri[:, 0]) + b2 * (w_tri[:, 2] - w_tri[:, 0])
    k0 = np.clip(np.floor((w - ow) / voxel).astype(np.int64) + 1, 0, nw)
    np.add.at(hist, (iu[hit], iv[hit], k0[hit]), 1)
    crossings = np.cumsum(hist[:, :, :nw], axis=2)
    odd = (crossings % 2) == 1  # indexed (u, v, w)
    order = np.argsort([u_ax, v_ax, axis])
    return np.transpose(odd, order)


def inside_grid(origin: np.ndarray, voxel: float, shape: tuple[int, int, int], vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``shape`` bool (indexed x, y, z): grid points ``origin + i * voxel`` inside the closed mesh (ray parity
    along x, y and z, majority vote)."""
    tri = np.asarray(vertices, dtype=np.float64)[faces]
    votes = np.zeros(shape, dtype=np.int8)
    for a in range(3):
        votes += _parity_along(a, origin, voxel, shape, tri)
    return votes >= 2


def cap_boundary_loops(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Close every boundary loop of the triangle set ``faces`` with a fan around the loop's centroid.

    Returns the vertices (the input plus one centroid per loop) and the faces (input plus caps), oriented
    like the input. Boundary edges are those used by one triangle only."""
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return np.asarray(vertices), faces
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = directed[:, 0] * (int(directed.max()) + 1) + directed[:, 1]
    rkey = directed[:, 1] * (int(directed.max()) + 1) + directed[:, 0]
    boundary = directed[~np.isin(key, rkey)]
    if len(boundary) == 0:
        return np.asarray(vertices), faces
    nxt: dict[int, list[int]] = {}
    for a, b in boundary.tolist():
        nxt.setdefault(a, []).append(b)
    verts = [np.asarray(vertices, dtype=np.float64)]
    caps = []
    n_vert = len(vertices)
    while nxt:
        start = next(iter(nxt))
        loop = [start]
        cur = start
        while True:
            outs = nxt.get(cur)
            if not outs:
                break
            b = outs.pop()
            if not outs:
                del nxt[cur]
            if b == start:
                break
            loop.append(b)
            cur = b
        if len(loop) < 3:
            continue
        centre = np.asarray(vertices, dtype=np.float64)[loop].mean(axis=0)
        verts.append(centre[None])
        c = n_vert
        n_vert += 1
        ring = np.asarray(loop + [loop[0]])
        # Boundary edge a->b belongs to a triangle oriented a->b; the cap uses b->a.
        caps.append(np.stack([ring[1:], ring[:-1], np.full(len(loop), c)], axis=1))
    if not caps:
        return np.asarray(vertices), faces
    return np.concatenate(verts), np.concatenate([faces] + caps)
