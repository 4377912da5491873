"""Which meshes of a character are its body and which are accessories (eyes, teeth, joint rings, garments, hair,
props). The rules are geometric and apply in order to every mesh but the largest (docs/meshes.md):

1. the only mesh, or the one with the largest surface, is the body (the primary body);
2. a mesh whose open boundary meets the primary body's open boundary is body too (a body split at the neck);
3. a mesh with most of its vertices inside the primary body is inner geometry (teeth, eyes, joint rings);
4. a mesh whose vertices lie inside the body or just outside it (within :data:`OVER_BAND_M`) is over it: a
   garment, hair, a glove;
5. a mesh of less than :data:`SMALL_AREA_SHARE` of the primary body's surface is small (eyes, lashes, buttons);
6. a mesh skinned to at most :data:`RIGID_JOINTS` joints is rigid (a blade, a bag, a helmet) following one bone;
7. any other mesh is body (large, skinned to many joints, neither inside nor over the body).

Lengths are at a 1.80 m character, scaled to the character's height. Inside/outside uses the nearest welded
vertex of the primary body and its area-weighted normal (the sign of ``(p - q) . n``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from retarget_core.character import Character, MeshInfo

REFERENCE_HEIGHT_M = 1.80
WELD_M = 1e-4  # vertices closer than this are one (UV and normal seams split glTF vertices)
STITCH_M = 0.002  # boundary vertices of two meshes this close are one seam
STITCHED_SHARE = 0.5  # share of a mesh's boundary vertices on the body's boundary: joined to it
INSIDE_SHARE = 0.5  # share of vertices inside the body: inner geometry
OVER_BAND_M = 0.06  # a garment's vertices lie inside the body or at most this far outside it
OVER_SHARE = 0.8
SMALL_AREA_SHARE = 0.10
RIGID_JOINTS = 2


@dataclass
class MeshSpan:
    """One mesh of the merged character: its name, its vertices ``start .. start + vertices`` and its
    triangles ``face_start .. face_start + faces`` in the merged arrays."""

    name: str
    start: int
    vertices: int
    face_start: int
    faces: int


@dataclass
class _Surface:
    """A mesh welded by position: points ``(N, 3)``, triangles ``(T, 3)``, the merged vertex of each point."""

    points: np.ndarray
    faces: np.ndarray
    area: float
    boundary: np.ndarray  # (B,) welded points on an edge used by one triangle only

    def normals(self) -> np.ndarray:
        """Area-weighted unit normals ``(N, 3)`` of the welded points."""
        tri = self.points[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        out = np.zeros_like(self.points)
        for k in range(3):
            np.add.at(out, self.faces[:, k], n)
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def _surface(vertices: np.ndarray, faces: np.ndarray) -> _Surface:
    """Weld ``vertices (N, 3)`` by position and find the open boundary of ``faces (T, 3)`` (local indices)."""
    key = np.round(vertices / WELD_M).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    points = vertices[first]
    f = inverse.reshape(-1)[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    tri = points[f]
    area = float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = np.unique(uniq[counts == 1]) if len(uniq) else np.zeros(0, dtype=np.int64)
    return _Surface(points, f, area, boundary)


def _spans_surfaces(character: Character, spans: list[MeshSpan]) -> list[_Surface]:
    verts = character.vertices.detach().double().numpy()
    faces = character.faces.numpy()
    out = []
    for s in spans:
        f = faces[s.face_start : s.face_start + s.faces] - s.start
        out.append(_surface(verts[s.start : s.start + s.vertices], f))
    return out


def _joints_used(character: Character, span: MeshSpan) -> int:
    """Distinct dominant joints of the mesh's vertices."""
    w = character.skin_weights[span.start : span.start + span.vertices]
    j = character.skin_joints[span.start : span.start + span.vertices]
    dominant = j.gather(1, w.argmax(1, keepdim=True))
    return int(torch.unique(dominant).numel())


class _Body:
    """The primary body: a KD-tree of its welded points, their normals and its open boundary."""

    def __init__(self, surface: _Surface) -> None:
        self.surface = surface
        self.tree = cKDTree(surface.points)
        self.normals = surface.normals()
        self.boundary_tree = cKDTree(surface.points[surface.boundary]) if len(surface.boundary) else None

    def sides(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point ``(N,)``: inside the body (bool) and its distance to the nearest body point."""
        d, i = self.tree.query(points, k=1)
        inside = np.einsum("ij,ij->i", points - self.surface.points[i], self.normals[i]) < 0
        return inside, d

    def stitched_share(self, surface: _Surface, tol: float) -> float:
        """Share of ``surface``'s open boundary points within ``tol`` of the body's open boundary."""
        if self.boundary_tree is None or len(surface.boundary) == 0:
            return 0.0
        d, _ = self.boundary_tree.query(surface.points[surface.boundary], k=1)
        return float((d <= tol).mean())


def _decide(body: _Body, surface: _Surface, joints: int, scale: float) -> tuple[str, str]:
    """Role and reason of one mesh other than the primary body (rules 2 to 7 of the module doc)."""
    body_name = "the body"
    if body.stitched_share(surface, STITCH_M * scale) >= STITCHED_SHARE:
        return "body", f"joined to {body_name} along its open boundary"
    inside, dist = body.sides(surface.points)
    share_in = float(inside.mean()) if len(inside) else 0.0
    if share_in >= INSIDE_SHARE:
        return "accessory", f"inner geometry: {100 * share_in:.0f}% of its vertices lie inside {body_name}"
    near_out = (~inside) & (dist <= OVER_BAND_M * scale)
    share_over = share_in + float(near_out.mean())
    if share_over >= OVER_SHARE:
        return "accessory", (f"over {body_name}: {100 * share_over:.0f}% of its vertices lie inside it or within "
                             f"{100 * OVER_BAND_M:.0f} cm outside (a garment, hair, a mouth)")  # fmt: skip
    share_area = surface.area / max(body.surface.area, 1e-12)
    if share_area < SMALL_AREA_SHARE:
        return "accessory", f"small: {100 * share_area:.1f}% of the surface of {body_name}"
    if joints <= RIGID_JOINTS:
        return "accessory", f"rigid: skinned to {joints} joint{'s' if joints > 1 else ''}, a prop or a rigid piece"
    return (
        "body",
        f"large ({100 * share_area:.0f}% of the body's surface, {joints} joints), not inside or over the body",
    )


def classify_meshes(character: Character, spans: list[MeshSpan]) -> list[MeshInfo]:
    """The role of every mesh ``spans`` (in vertex order, covering the character's vertices)."""
    if not spans:
        return []
    if len(spans) == 1:
        s = spans[0]
        return [MeshInfo(s.name, "body", "the only mesh", s.vertices, s.faces, s.start)]
    surfaces = _spans_surfaces(character, spans)
    primary = max(range(len(spans)), key=lambda k: (surfaces[k].area, spans[k].vertices))
    body = _Body(surfaces[primary])
    extent = character.vertices.max(0).values - character.vertices.min(0).values
    scale = float(extent.max()) / REFERENCE_HEIGHT_M  # read before normalising: any unit, any up axis
    out = []
    for k, (s, surface) in enumerate(zip(spans, surfaces, strict=True)):
        joints = _joints_used(character, s)
        if k == primary:
            role, reason = "body", f"the largest surface ({surface.area:.2f} m^2, {joints} joints)"
        else:
            role, reason = _decide(body, surface, joints, scale)
        out.append(MeshInfo(s.name, role, reason, s.vertices, s.faces, s.start))
    return out


def with_mesh_roles(character: Character, spans: list[MeshSpan]) -> Character:
    """``character`` with :attr:`Character.meshes` and :attr:`Character.mesh_of_vertex` set from ``spans``."""
    meshes = classify_meshes(character, spans)
    of_vertex = torch.zeros(character.num_vertices, dtype=torch.long)
    for k, s in enumerate(spans):
        of_vertex[s.start : s.start + s.vertices] = k
    character.meshes, character.mesh_of_vertex = meshes, of_vertex
    return character


__all__ = ["MeshSpan", "classify_meshes", "with_mesh_roles"]
