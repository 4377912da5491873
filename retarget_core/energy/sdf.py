"""Per-body-part signed distance fields (paper 2, section 4) and the penetration queries built on them.

Each segment (see :mod:`retarget_core.body_parts`) gets a voxel grid in the rest pose, which is its joint's
rigid frame up to a fixed transform. A grid stores two channels at every voxel centre:

- the signed distance to the segment's closed mesh (its triangles plus a fan over each cut), and
- the signed distance to the whole character's rest mesh (the "Character SDF").

A posed point is taken back to segment ``j``'s rest frame by the inverse of ``j``'s skinning transform and the
grid is sampled trilinearly (``torch.nn.functional.grid_sample``, differentiable in the point). The two
channels are blended as paper 2's Blended SDF (its eq. 4) so the cut faces of a segment, which lie inside the
body, do not make deep penetrations near a segment boundary look shallow:

    p = clamp(SDF_seg / nu, 0, 1),   SDF_b = p * SDF_seg + (1 - p) * SDF_char.

Outside its grid a segment's distance is extrapolated as ``SDF(clamp(x)) + |x - clamp(x)|`` (an upper bound,
continuous); grids extend ``margin`` beyond the segment, so distances up to the margin are exact.

Choices where the papers leave room (all lengths given at a 1.80 m character and scaled to the body):
- grid voxel at least 4 mm and at most ``max_voxels`` voxels per segment; margin 3 cm; blend width nu 2 cm
  (paper 2 uses 0.1 shoulder heights, which lets the rest body shorten distances 14 cm away);
- penetration depth of a vertex into a segment is measured beyond what the same vertex already has in the
  bind pose (bodies whose thighs or arms touch at rest are not penalised for that), and is weighted by a
  geodesic ramp ``clamp((g - 3 cm) / (10 cm - 3 cm), 0, 1)`` where ``g`` is the geodesic distance on the rest
  mesh from the vertex to the segment. This stands in for paper 1's geodesic weights w_ri (its eq. 5):
  penetration in a joint fold (armpit, crotch, the neck's crease: within 3 cm of the segment, the band the
  acceptance measure leaves out) does not count, close to it counts little, between distant parts fully.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as nnf
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from torch import Tensor

from retarget_core import kinematics
from retarget_core.body_parts import BodyParts
from retarget_core.character import Character
from retarget_core.energy.mesh_distance import MeshDistance, cap_boundary_loops, signed_distance_grid
from retarget_core.energy.sdf_kernel import sample_grid

REFERENCE_HEIGHT_M = 1.80


@dataclass(frozen=True)
class SDFParams:
    """Grid and weighting parameters, lengths at a 1.80 m character (scaled to the body's height)."""

    min_voxel_m: float = 0.004
    max_voxels: int = 30_000
    margin_m: float = 0.03
    blend_m: float = 0.02
    geodesic_ramp_m: float = 0.10
    # Joint folds: a vertex this close along the rest mesh to a segment is in the fold between them (armpit,
    # crotch, the neck's crease); LBS sinks such skin into the neighbour at every bend, which no one calls a
    # penetration. 3 cm is the band the acceptance measure leaves out (../shared/ACCEPTANCE.md); the ramp then
    # rises from 0 here to 1 at geodesic_ramp_m. Renders: benchmarks/diag/results/pen_*.png.
    geodesic_dead_zone_m: float = 0.03
    sample_spacing_m: float = 0.02
    cluster_m: float = 0.04


@dataclass
class VertexClusters:
    """Vertices grouped into small clusters of one part each (rest-pose voxels of ``size``).

    of_vertex: ``(V,)`` cluster of each vertex; part: ``(C,)`` part of each cluster; members: ``(C, K)`` vertex
    indices padded with -1; radius: ``(C,)`` bound of the distance of a posed member from the posed centroid
    (1.25 times the rest-pose bound plus a quarter voxel: skinning bends clusters at joints)."""

    of_vertex: Tensor
    part: Tensor
    members: Tensor
    radius: Tensor


def vertex_clusters(vertices: Tensor, vertex_part: Tensor, size: float, max_members: int = 32) -> VertexClusters:
    """Clusters of the vertices of each part falling in the same rest-pose voxel of edge ``size``, split so
    that none has more than ``max_members`` vertices (dense regions such as faces and fingers)."""
    cell = torch.floor(vertices / size).long()
    cell = cell - cell.min(0).values
    dims = cell.max(0).values + 1
    key = ((vertex_part * dims[0] + cell[:, 0]) * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, voxel_of = torch.unique(key, return_inverse=True)
    slot = _slots(voxel_of)
    _, of_vertex = torch.unique(voxel_of * (len(vertices) + 1) + slot // max_members, return_inverse=True)
    c_n = int(of_vertex.max()) + 1
    part = torch.zeros(c_n, dtype=torch.long).scatter_(0, of_vertex, vertex_part)
    members = torch.full((c_n, max_members), -1, dtype=torch.long)
    members[of_vertex, _slots(of_vertex)] = torch.arange(len(vertices))
    keep = (members >= 0).any(0)
    centre = torch.zeros(c_n, 3, dtype=vertices.dtype).index_add_(0, of_vertex, vertices)
    centre = centre / torch.bincount(of_vertex, minlength=c_n).to(vertices.dtype)[:, None]
    spread = (vertices - centre[of_vertex]).norm(dim=-1)
    radius = torch.zeros(c_n, dtype=vertices.dtype).scatter_reduce_(0, of_vertex, spread, "amax")
    return VertexClusters(of_vertex, part, members[:, keep], 1.25 * radius + 0.25 * size)


def _slots(group: Tensor) -> Tensor:
    """Rank ``(N,)`` of every element within its group (0, 1, ... in index order)."""
    order = torch.argsort(group, stable=True)
    counts = torch.bincount(group)
    start = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(group)
    slot[order] = torch.arange(len(group)) - start[group[order]]
    return slot


@dataclass
class PartSDF:
    """Signed distance grids of every segment of one character, plus per-vertex data for the queries.

    grids: per segment ``(2, Nz, Ny, Nx)`` [segment SDF, character SDF] or None for a segment without triangles.
    origin: ``(S, 3)`` rest-pose position of voxel (0, 0, 0); voxel: ``(S,)`` edge length; size: ``(S, 3)``
        voxels along x, y, z.
    rest_depth: ``(V, S)`` penetration depth of each vertex into each segment in the bind pose (subtracted).
    geodesic_weight: ``(V, S)`` the geodesic ramp weight in 0..1 (see module doc).
    vertex_area: ``(V,)`` a third of the area of the rest triangles around each vertex (m^2).
    allowed: ``(S, S)`` pairs measured (see :meth:`BodyParts.collision_mask`).
    clusters: small groups of nearby vertices of one part each, for culling (see :func:`vertex_clusters`).
    """

    parts: BodyParts
    grids: list[Tensor | None]
    origin: Tensor
    voxel: Tensor
    size: Tensor
    rest_depth: Tensor
    geodesic_weight: Tensor
    vertex_area: Tensor
    allowed: Tensor
    height: float
    blend: float
    margin: float
    clusters: VertexClusters | None = None

    @property
    def scale_to_180(self) -> float:
        """Factor taking this body's lengths to a 1.80 m character."""
        return REFERENCE_HEIGHT_M / self.height

    def grid_corners(self) -> Tensor:
        """Rest-pose corners ``(S, 8, 3)`` of every grid."""
        extent = (self.size - 1).to(self.origin.dtype) * self.voxel[:, None]
        bits = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=self.origin.dtype)
        return self.origin[:, None, :] + bits[None] * extent[:, None, :]


def vertex_areas(vertices: Tensor, faces: Tensor) -> Tensor:
    """A third of the area of the triangles around each vertex ``(V,)``."""
    tri = vertices[faces]
    area = 0.5 * torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1).norm(dim=-1)
    out = torch.zeros(vertices.shape[0], dtype=vertices.dtype)
    for k in range(3):
        out.index_add_(0, faces[:, k], area / 3.0)
    return out


def geodesic_to_parts(vertices: np.ndarray, faces: np.ndarray, vertex_part: np.ndarray, num_parts: int, limit: float) -> np.ndarray:
    """Geodesic (edge-path) distance ``(V, S)`` from every vertex to the nearest vertex of each part, computed
    up to ``limit`` (larger distances and other connected pieces give ``inf``)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    length = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    n = len(vertices)
    graph = coo_matrix((length, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    out = np.full((n, num_parts), np.inf)
    for s in range(num_parts):
        src = np.nonzero(vertex_part == s)[0]
        if len(src):
            out[:, s] = dijkstra(graph, directed=False, indices=src, min_only=True, limit=limit)
    return out


def geodesic_ramp(geodesic: np.ndarray, dead_zone: float, ramp: float) -> np.ndarray:
    """Weight in 0..1 of a penetration at rest-surface distance ``geodesic`` (any shape, m) from the segment it
    enters: 0 up to ``dead_zone`` (joint folds), rising linearly to 1 at ``ramp`` and beyond (``inf`` gives 1)."""
    return np.clip((geodesic - dead_zone) / max(ramp - dead_zone, 1e-12), 0.0, 1.0)


def build_part_sdf(character: Character, parts: BodyParts, params: SDFParams | None = None) -> PartSDF:
    """Precompute the grids of every segment of ``character`` (the slow part of a body's first job; cached by :mod:`retarget_core.body_cache`)."""
    params = params or SDFParams()
    height = character.height
    s = height / REFERENCE_HEIGHT_M
    verts = character.vertices.detach().double().numpy()
    faces = character.faces.numpy().astype(np.int64)
    face_part = parts.face_part.numpy()
    spacing = params.sample_spacing_m * s
    full = MeshDistance(verts, faces, spacing)
    blend = params.blend_m * s
    margin = params.margin_m * s
    grids: list[Tensor | None] = []
    origins, voxels, sizes = [], [], []
    for seg in range(parts.num_parts):
        pf = faces[face_part == seg]
        if len(pf) == 0:
            grids.append(None)
            origins.append(np.zeros(3))
            voxels.append(1.0)
            sizes.append(np.ones(3, dtype=np.int64))
            continue
        cv, cf = cap_boundary_loops(verts, pf)
        used = cv[np.unique(cf)]
        lo, hi = used.min(0) - margin, used.max(0) + margin
        vox = max(params.min_voxel_m * s, float(np.prod(hi - lo) / params.max_voxels) ** (1.0 / 3.0))
        size = np.ceil((hi - lo) / vox).astype(np.int64) + 1
        seg_sd = signed_distance_grid(lo, vox, tuple(size), MeshDistance(cv, cf, spacing))
        char_sd = signed_distance_grid(lo, vox, tuple(size), full)
        # Far outside the segment the blend uses the segment channel alone.
        char_sd = np.where(seg_sd < blend, char_sd, seg_sd)
        vol = np.stack([seg_sd, char_sd]).reshape(2, *size)  # (2, x, y, z)
        grids.append(torch.from_numpy(np.ascontiguousarray(vol.transpose(0, 3, 2, 1))).float())
        origins.append(lo)
        voxels.append(vox)
        sizes.append(size)
    allowed = parts.collision_mask(ignore_arm_chest=False)
    geo = geodesic_to_parts(verts, faces, parts.vertex_part.numpy(), parts.num_parts, params.geodesic_ramp_m * s)
    geo_w = torch.from_numpy(geodesic_ramp(geo, params.geodesic_dead_zone_m * s, params.geodesic_ramp_m * s)).float()
    sdf = PartSDF(
        parts=parts,
        grids=grids,
        origin=torch.tensor(np.stack(origins), dtype=torch.float32),
        voxel=torch.tensor(voxels, dtype=torch.float32),
        size=torch.tensor(np.stack(sizes), dtype=torch.long),
        rest_depth=torch.zeros(len(verts), parts.num_parts),
        geodesic_weight=geo_w,
        vertex_area=vertex_areas(character.vertices.float(), character.faces),
        allowed=allowed,
        height=height,
        blend=blend,
        margin=margin,
        clusters=vertex_clusters(character.vertices.float(), parts.vertex_part, params.cluster_m * s),
    )
    rest = character.vertices.float()[None]
    eye = torch.eye(3, 4).expand(1, parts.num_parts, 3, 4)
    with torch.no_grad():
        samples = sample_pairs(sdf, rest, eye, allowed)
        depth = (-samples.distance).clamp_min(0.0)
        sdf.rest_depth[samples.vertex, samples.part] = depth
    return sdf


def segment_matrices(character: Character, parts: BodyParts, global_rotations: Tensor, global_positions: Tensor) -> Tensor:
    """Skinning transforms ``(F, S, 3, 4)`` (rest world -> posed world) of the segments' joints from world
    joint rotations ``(F, J, 4)`` and positions ``(F, J, 3)``."""
    rest_rot, rest_pos = character.skeleton.rest_global()
    idx = torch.tensor(parts.joints, dtype=torch.long)
    return kinematics.skinning_matrices(rest_rot[idx], rest_pos[idx], global_rotations[..., idx, :], global_positions[..., idx, :])


@dataclass
class PairSamples:
    """Signed distances of posed vertices to the segments whose grids they may touch.

    frame, vertex, part: ``(N,)`` indices; distance: ``(N,)`` blended signed distance of vertex ``vertex`` at
    ``frame`` to segment ``part`` (metres, negative inside), differentiable in the posed inputs."""

    frame: Tensor
    vertex: Tensor
    part: Tensor
    distance: Tensor


def _sample_grid(sdf: PartSDF, seg: int, x: Tensor, channel: int | None = None) -> Tensor:
    """Blended signed distance ``(N,)`` of rest-frame points ``x (N, 3)`` to segment ``seg`` (``channel`` 0
    or 1: the segment or character channel alone)."""
    grid = sdf.grids[seg]
    assert grid is not None
    if channel is None and x.device.type == "cpu" and grid.device.type == "cpu" and min(grid.shape[1:]) >= 2:
        return sample_grid(grid, sdf.origin[seg], float(sdf.voxel[seg]), sdf.blend, x)  # compiled; float64 inside
    size = sdf.size[seg].to(x.dtype)
    extent = (size - 1) * sdf.voxel[seg]
    lo = sdf.origin[seg].to(x.dtype)
    inside = torch.minimum(torch.maximum(x, lo), lo + extent)
    outside = (x - inside).norm(dim=-1)
    norm = 2.0 * (inside - lo) / extent.clamp_min(1e-12) - 1.0
    g = grid[None] if channel is None else grid[None, channel : channel + 1]
    vals = nnf.grid_sample(g.to(x.dtype), norm.view(1, 1, 1, -1, 3), mode="bilinear", align_corners=True)
    if channel is not None:
        return vals.view(-1) + outside
    seg_d, char_d = vals.view(2, -1)
    p = (seg_d / sdf.blend).clamp(0.0, 1.0)
    return p * seg_d + (1.0 - p) * char_d + outside


@dataclass
class _PairCull:
    """What :func:`sample_pairs` culls with, per frame: ``overlap (F, Si, Sj)`` part box against segment grid box,
    cluster centres ``centre (F * C, 3)`` and radii ``radius (F * C,)`` (flat), the grids' rest boxes ``lo, hi
    (S, 3)``, and ``slot (V,)`` mesh vertex -> row of ``posed`` when a vertex subset is given."""

    clusters: VertexClusters
    overlap: Tensor
    centre: Tensor
    radius: Tensor
    lo: Tensor
    hi: Tensor
    slot: Tensor | None


def sample_pairs(
    sdf: PartSDF,
    posed: Tensor,
    seg_mats: Tensor,
    allowed: Tensor | None = None,
    vertices: Tensor | None = None,
    inside_only: bool = False,
) -> PairSamples:
    """Blended signed distances of posed body vertices ``(F, V, 3)`` to segments, for every allowed pair (vertex
    part i, segment j) where the vertex may lie within the grid margin of j. ``seg_mats (F, S, 3, 4)`` from
    :func:`segment_matrices`. Vertices not sampled are farther from the segment than the grid margin.
    ``vertices (N,)``: when given, ``posed`` is ``(F, N, 3)``, those vertices only (they must include every
    vertex of a part with an allowed pair); the samples still name vertices by their index in the mesh.
    ``inside_only``: only clusters that may hold a vertex with a negative blended distance are sampled (a
    depth check's needs; the blend is the segment channel alone, so positive, beyond the blend width).

    Culling, coarse to fine: the posed bounding box of part i against that of j's grid, per frame; then each
    cluster of nearby vertices (:class:`VertexClusters`), bounded by a sphere around its posed centroid,
    against j's grid box in j's frame; then the sphere against j's segment distance at its centre.
    """
    allowed = sdf.allowed if allowed is None else allowed
    if sdf.clusters is None and vertices is not None:
        raise ValueError("sample_pairs: a vertex subset needs the SDF's precomputed clusters")
    reach = sdf.blend if inside_only else sdf.margin
    if _compiled_path(sdf, posed, seg_mats):
        arrays = _float64_arrays(posed, seg_mats)
        cull = _compiled_cull(sdf, arrays, posed.dtype, allowed, vertices)
        return body_samples(sdf, _compiled_samples(sdf, cull, arrays, posed.dtype, reach))
    cull = _pair_cull(sdf, posed.detach(), seg_mats.detach(), allowed, vertices)
    n_pts = posed.shape[1]
    rot, trans = seg_mats[..., :3], seg_mats[..., 3]  # (F, S, 3, 3), (F, S, 3)
    frames, verts, segs, dists = [], [], [], []
    # Gathers use index_select on flattened tensors: advanced indexing is far slower on small CPUs.
    flat_posed = posed.reshape(-1, 3)
    for j in torch.nonzero(cull.overlap.any(dim=(0, 1))).flatten().tolist():
        found = _segment_candidates(sdf, cull, rot.detach(), trans.detach(), j, reach)
        if found is None:
            continue
        f_idx, v_idx = found
        rows = v_idx if cull.slot is None else cull.slot.index_select(0, v_idx)
        x = flat_posed.index_select(0, f_idx * n_pts + rows)
        rot_j, trans_j = rot[:, j].contiguous(), trans[:, j].contiguous()
        local = torch.einsum("nji,nj->ni", rot_j.index_select(0, f_idx), x - trans_j.index_select(0, f_idx))
        frames.append(f_idx)
        verts.append(v_idx)
        segs.append(torch.full_like(f_idx, j))
        dists.append(_sample_grid(sdf, j, local))
    if not frames:
        empty = torch.zeros(0, dtype=torch.long)
        return PairSamples(empty, empty, empty, posed.new_zeros(0))
    return body_samples(sdf, PairSamples(torch.cat(frames), torch.cat(verts), torch.cat(segs), torch.cat(dists)))


def _compiled_path(sdf: PartSDF, posed: Tensor, seg_mats: Tensor) -> bool:
    """Whether :func:`sample_pairs` can take the compiled path: no gradient asked, CPU tensors, and every grid at
    least two voxels along each axis."""
    if posed.requires_grad or seg_mats.requires_grad or posed.device.type != "cpu":
        return False
    return all(g is None or (g.device.type == "cpu" and min(g.shape[1:]) >= 2) for g in sdf.grids)


def _float64_arrays(posed: Tensor, seg_mats: Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The compiled path's inputs, converted once: posed points ``(F, N, 3)``, segment rotations ``(F, S, 3, 3)``
    and translations ``(F, S, 3)``, float64."""
    mats = seg_mats.detach().double()
    pts = posed.detach().double().contiguous().numpy()
    return pts, mats[..., :3].contiguous().numpy(), mats[..., 3].contiguous().numpy()


def _compiled_samples(sdf: PartSDF, cull: _PairCull, arrays: tuple[np.ndarray, np.ndarray, np.ndarray],
                      dtype: torch.dtype, reach: float) -> PairSamples:  # fmt: skip
    """:func:`sample_pairs`' candidates and distances (in ``dtype``), segment by segment through the compiled
    search (:func:`retarget_core.energy.pair_samples_kernel.segment_samples`); the same samples, in the same order."""
    from retarget_core.energy.pair_samples_kernel import segment_samples

    pts, rot, trans = arrays
    f_n = pts.shape[0]
    clusters = cull.clusters
    centre = cull.centre.view(f_n, -1, 3).double().contiguous().numpy()
    radius = cull.radius.view(f_n, -1)[0].double().numpy() if f_n else np.zeros(0)
    members = clusters.members.numpy()
    slot = cull.slot.numpy() if cull.slot is not None else np.zeros(0, dtype=np.int64)
    box_lo, box_hi = cull.lo.double().numpy(), cull.hi.double().numpy()
    frames, verts, segs, dists = [], [], [], []
    for j in torch.nonzero(cull.overlap.any(dim=(0, 1))).flatten().tolist():
        grid = sdf.grids[j]
        assert grid is not None  # overlap holds segments with a grid only
        cand = cull.overlap[:, :, j].index_select(1, clusters.part).numpy()
        f, v, d = segment_samples(grid.detach().numpy(), sdf.origin[j].double().numpy(), float(sdf.voxel[j]),
                                  float(sdf.blend), box_lo[j], box_hi[j], rot[:, j], trans[:, j], pts, cand, centre,
                                  radius, members, slot, float(reach))  # fmt: skip
        frames.append(torch.from_numpy(f))
        verts.append(torch.from_numpy(v))
        segs.append(torch.full((len(f),), j, dtype=torch.long))
        dists.append(torch.from_numpy(d).to(dtype))
    if not frames:
        empty = torch.zeros(0, dtype=torch.long)
        return PairSamples(empty, empty, empty, torch.zeros(0, dtype=dtype))
    return PairSamples(torch.cat(frames), torch.cat(verts), torch.cat(segs), torch.cat(dists))


def _bounded_rows(vp: Tensor, allowed: Tensor, vertices: Tensor | None, n_pts: int) -> tuple[Tensor | None, Tensor | None]:
    """The mesh vertices :func:`sample_pairs` bounds and clusters ``(R,)`` (None: all) and, for a vertex subset,
    ``slot (V,)`` mesh vertex -> row of the posed points. Only the vertices of parts with an allowed pair are
    bounded (a leg-only check skips the rest of the body); the others' boxes stay empty and their clusters are
    never candidates."""
    if vertices is not None:
        return vertices, torch.full((vp.shape[0],), -1, dtype=torch.long).index_copy_(0, vertices, torch.arange(n_pts))
    active = allowed.any(dim=1).index_select(0, vp)
    return (None if bool(active.all()) else torch.nonzero(active).flatten()), None


def _compiled_cull(sdf: PartSDF, arrays: tuple[np.ndarray, np.ndarray, np.ndarray], dtype: torch.dtype,
                   allowed: Tensor, vertices: Tensor | None) -> _PairCull:  # fmt: skip
    """:func:`_pair_cull` through the compiled kernel (:func:`retarget_core.energy.pair_samples_kernel.pair_cull`;
    float64) on :func:`_float64_arrays` of points posed in ``dtype``."""
    from retarget_core.energy.pair_samples_kernel import pair_cull

    pts, rot, trans = arrays
    f_n, n_pts = pts.shape[:2]
    vp = sdf.parts.vertex_part
    clusters = sdf.clusters or vertex_clusters(torch.from_numpy(pts[0]).to(dtype), vp, 0.04)  # as the tensor path
    sub, slot = _bounded_rows(vp, allowed, vertices, n_pts)
    mesh = torch.arange(n_pts) if sub is None else sub  # the bounded vertices
    rows = mesh if vertices is None else torch.arange(n_pts)  # ... as rows of posed
    has_grid = torch.tensor([g is not None for g in sdf.grids])
    overlap, centre = pair_cull(pts, rows.numpy(), vp.index_select(0, mesh).numpy(),
                                clusters.of_vertex.index_select(0, mesh).numpy(), clusters.part.shape[0],
                                sdf.grid_corners().double().numpy(), rot, trans, allowed.numpy(),
                                has_grid.numpy())  # fmt: skip
    lo = sdf.origin.double()
    hi = lo + (sdf.size - 1).double() * sdf.voxel[:, None].double()
    radius = clusters.radius.double()[None].expand(f_n, -1).reshape(-1)
    return _PairCull(clusters, torch.from_numpy(overlap), torch.from_numpy(centre).reshape(-1, 3), radius, lo, hi, slot)


@torch.no_grad()
def _pair_cull(sdf: PartSDF, p: Tensor, seg_mats: Tensor, allowed: Tensor, vertices: Tensor | None) -> _PairCull:
    """The per-frame bounds of :func:`sample_pairs` for posed points ``p (F, N, 3)``."""
    f_n, n_pts = p.shape[:2]
    vp = sdf.parts.vertex_part
    s_n = sdf.parts.num_parts
    clusters = sdf.clusters or vertex_clusters(p[0], vp, 0.04)
    r_all, t_all = seg_mats[..., :3], seg_mats[..., 3]
    c_n = clusters.part.shape[0]
    sub, slot = _bounded_rows(vp, allowed, vertices, n_pts)
    box_points = p if sub is None or vertices is not None else p.index_select(1, sub)
    vp_a = vp if sub is None else vp.index_select(0, sub)
    ov = clusters.of_vertex if sub is None else clusters.of_vertex.index_select(0, sub)
    idx = vp_a.view(1, -1, 1).expand(f_n, -1, 3)
    p_lo = torch.full((f_n, s_n, 3), math.inf, dtype=p.dtype).scatter_reduce(1, idx, box_points, "amin")
    p_hi = torch.full((f_n, s_n, 3), -math.inf, dtype=p.dtype).scatter_reduce(1, idx, box_points, "amax")
    corners = sdf.grid_corners().to(p.dtype)  # (S, 8, 3)
    posed_corners = torch.einsum("fsij,skj->fski", r_all, corners) + t_all[:, :, None, :]
    g_lo, g_hi = posed_corners.min(dim=2).values, posed_corners.max(dim=2).values
    overlap = ((p_lo[:, :, None] <= g_hi[:, None]) & (p_hi[:, :, None] >= g_lo[:, None])).all(-1)  # (F, Si, Sj)
    has_grid = torch.tensor([g is not None for g in sdf.grids])
    overlap &= allowed[None] & has_grid[None, None, :]
    counts = torch.bincount(ov, minlength=c_n).clamp_min(1).to(p.dtype)
    centre = torch.zeros(f_n, c_n, 3, dtype=p.dtype).index_add_(1, ov, box_points) / counts[None, :, None]
    radius = clusters.radius.to(p.dtype)[None].expand(f_n, c_n)
    lo = sdf.origin.to(p.dtype)
    hi = lo + (sdf.size - 1).to(p.dtype) * sdf.voxel[:, None].to(p.dtype)
    return _PairCull(clusters, overlap, centre.reshape(-1, 3), radius.reshape(-1), lo, hi, slot)


@torch.no_grad()
def _segment_candidates(sdf: PartSDF, cull: _PairCull, r_all: Tensor, t_all: Tensor, j: int,
                        reach: float) -> tuple[Tensor, Tensor] | None:  # fmt: skip
    """(frame, mesh vertex) ``(N,)`` each of the clusters that may hold a vertex within ``reach`` of segment
    ``j``; ``r_all, t_all`` ``(F, S, 3, 3)``, ``(F, S, 3)``. None when no cluster does."""
    clusters = cull.clusters
    c_n = clusters.part.shape[0]
    cand = cull.overlap[:, :, j].contiguous().index_select(1, clusters.part)  # (F, C)
    f_c, c_sel = torch.nonzero(cand, as_tuple=True)  # candidate (frame, cluster)
    key = f_c * c_n + c_sel
    r_j = r_all[:, j].contiguous().index_select(0, f_c)
    t_j = t_all[:, j].contiguous().index_select(0, f_c)
    centre_local = torch.einsum("nji,nj->ni", r_j, cull.centre.index_select(0, key) - t_j)
    rad = cull.radius.index_select(0, key)
    keep = (centre_local - centre_local.clamp(cull.lo[j], cull.hi[j])).norm(dim=-1) <= rad
    # The segment channel is 1-Lipschitz: a cluster whose centre is farther than margin + radius from the
    # segment has every vertex beyond the margin (where the blend is the segment channel alone).
    f_c, c_sel, centre_local, rad = f_c[keep], c_sel[keep], centre_local[keep], rad[keep]
    keep = _sample_grid(sdf, j, centre_local, channel=0) - rad <= reach
    f_c, c_sel = f_c[keep], c_sel[keep]
    if len(f_c) == 0:
        return None
    mem = clusters.members.index_select(0, c_sel)  # (N', K)
    valid = mem >= 0
    return f_c[:, None].expand_as(mem).masked_select(valid), mem.masked_select(valid)


def body_samples(sdf: PartSDF, samples: PairSamples) -> PairSamples:
    """``samples`` of body vertices only: accessory meshes (eyes, garments, props) are never tested."""
    body = sdf.parts.body
    if body is None:
        return samples
    if body.shape[0] != sdf.parts.vertex_part.shape[0]:
        raise ValueError("the parts' body mask and vertices differ in length: a vertex subset must subset both")
    keep = body.index_select(0, samples.vertex)
    return PairSamples(samples.frame[keep], samples.vertex[keep], samples.part[keep], samples.distance[keep])


def segment_distance(sdf: PartSDF, seg: int, points: Tensor) -> Tensor:
    """Blended signed distance ``(N,)`` of points ``(N, 3)`` given in segment ``seg``'s rest frame (posed points
    taken back by the inverse of the segment's skinning transform); differentiable in the points."""
    return _sample_grid(sdf, seg, points)


def _pair_values(table: Tensor, samples: PairSamples) -> Tensor:
    """``table (V, S)`` at each sample's (vertex, part)."""
    return table.reshape(-1).index_select(0, samples.vertex * table.shape[1] + samples.part)


def effective_depth(sdf: PartSDF, samples: PairSamples, subtract_rest: bool = True, geodesic: bool = True) -> Tensor:
    """Per sample ``(N,)``: penetration depth (m, >= 0) beyond the bind pose's, times the geodesic weight."""
    depth = -samples.distance
    if subtract_rest:
        depth = depth - _pair_values(sdf.rest_depth, samples).to(depth.dtype)
    depth = depth.clamp_min(0.0)
    if geodesic:
        depth = depth * _pair_values(sdf.geodesic_weight, samples).to(depth.dtype)
    return depth


def vertex_depths(sdf: PartSDF, samples: PairSamples, frames: int) -> Tensor:
    """Deepest weighted penetration of every vertex ``(F, V)`` (m) over the segments it is tested against."""
    v_n = sdf.rest_depth.shape[0]
    depth = effective_depth(sdf, samples)
    out = depth.new_zeros(frames * v_n)
    return out.scatter_reduce(0, samples.frame * v_n + samples.vertex, depth, "amax", include_self=True).view(frames, v_n)


def distance_matrix(sdf: PartSDF, samples: PairSamples, frames: int) -> Tensor:
    """Paper 2's M_dist ``(F, S, S)``: the smallest signed distance of segment i's vertices to segment j
    (m, unweighted, bind pose not subtracted), capped at the grid margin (also where nothing was sampled)."""
    s_n = sdf.parts.num_parts
    key = (samples.frame * s_n + sdf.parts.vertex_part.index_select(0, samples.vertex)) * s_n + samples.part
    out = samples.distance.new_full((frames * s_n * s_n,), sdf.margin)
    out = out.scatter_reduce(0, key, samples.distance.clamp_max(sdf.margin), "amin", include_self=True)
    return out.view(frames, s_n, s_n)


__all__ = [
    "REFERENCE_HEIGHT_M",
    "VertexClusters",
    "vertex_clusters",
    "PairSamples",
    "PartSDF",
    "SDFParams",
    "build_part_sdf",
    "distance_matrix",
    "effective_depth",
    "geodesic_ramp",
    "geodesic_to_parts",
    "sample_pairs",
    "segment_distance",
    "segment_matrices",
    "vertex_areas",
    "vertex_depths",
]
