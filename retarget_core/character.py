"""Character: a skinned triangle mesh on a skeleton, in metres, Y up, facing +Z, feet on y = 0."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.geometry.skinning_kernel import sparse_skinning
from retarget_core.skeleton import Skeleton


@dataclass
class Material:
    """The surface look carried from input to output: a base colour and an optional base-colour image."""

    base_color: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    image_bytes: bytes | None = None
    image_mime: str | None = None
    metallic: float = 0.0
    roughness: float = 0.8


MESH_ROLES: tuple[str, ...] = ("body", "accessory")


@dataclass
class MeshInfo:
    """One mesh of a character and the role decided for it (docs/meshes.md).

    role: ``body`` (measured and tested for penetration) or ``accessory`` (follows the skin, never tested);
    reason: one sentence saying which rule decided; vertices, faces: its counts; start: its first vertex in the
    merged mesh (its vertices are ``start .. start + vertices``)."""

    name: str
    role: str
    reason: str
    vertices: int
    faces: int
    start: int = 0

    def __post_init__(self) -> None:
        if self.role not in MESH_ROLES:
            raise ValueError(f"mesh role must be one of {MESH_ROLES}, not {self.role!r}")

    def as_dict(self) -> dict[str, object]:
        return {"name": self.name, "role": self.role, "reason": self.reason, "vertices": self.vertices,
                "faces": self.faces}  # fmt: skip


@dataclass
class Character:
    """A skinned body.

    vertices: ``(V, 3)`` positions in the skeleton's rest pose (world space).
    faces: ``(T, 3)`` vertex indices of triangles (int64).
    skin_joints: ``(V, K)`` joint indices into ``skeleton`` (int64).
    skin_weights: ``(V, K)`` weights, each row summing to 1.
    uvs: ``(V, 2)`` texture coordinates or None.
    meshes: the meshes merged into this one, in vertex order, with their roles (empty: one body mesh).
    mesh_of_vertex: ``(V,)`` index into ``meshes`` of each vertex, or None when ``meshes`` is empty.
    """

    name: str
    skeleton: Skeleton
    vertices: Tensor
    faces: Tensor
    skin_joints: Tensor
    skin_weights: Tensor
    uvs: Tensor | None = None
    material: Material = field(default_factory=Material)
    meshes: list[MeshInfo] = field(default_factory=list)
    mesh_of_vertex: Tensor | None = None

    def __post_init__(self) -> None:
        v = self.vertices.shape[0]
        if self.vertices.shape != (v, 3) or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError("vertices must be (V, 3) and faces (T, 3)")
        if self.skin_joints.shape != self.skin_weights.shape or self.skin_joints.shape[0] != v:
            raise ValueError("skin_joints and skin_weights must both be (V, K)")
        if self.meshes and (self.mesh_of_vertex is None or self.mesh_of_vertex.shape != (v,)):
            raise ValueError("meshes need mesh_of_vertex (V,)")

    @property
    def body_vertices(self) -> Tensor:
        """``(V,)`` bool: vertices of the meshes whose role is ``body`` (all of them without mesh roles)."""
        if not self.meshes or self.mesh_of_vertex is None:
            return torch.ones(self.num_vertices, dtype=torch.bool)
        body = torch.tensor([m.role == "body" for m in self.meshes], dtype=torch.bool)
        return body.index_select(0, self.mesh_of_vertex)

    @property
    def has_accessories(self) -> bool:
        """Some mesh is an accessory (see :class:`MeshInfo`)."""
        return any(m.role != "body" for m in self.meshes)

    def body_faces(self) -> Tensor:
        """``(T_b, 3)`` the triangles whose three vertices are body vertices."""
        if not self.has_accessories:
            return self.faces
        return self.faces[self.body_vertices[self.faces].all(dim=1)]

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def height(self) -> float:
        """Height of the rest pose in metres (vertical extent of the mesh)."""
        return float(self.vertices[:, 1].max() - self.vertices[:, 1].min())

    def dense_weights(self) -> Tensor:
        """Skinning weights as a dense ``(V, J)`` matrix."""
        return kinematics.dense_weights(self.skin_joints, self.skin_weights, self.skeleton.num_joints)

    def pose_vertices(self, global_rotations: Tensor, global_positions: Tensor) -> Tensor:
        """Posed vertices ``(..., V, 3)`` for world joint transforms ``(..., J, 4)`` and ``(..., J, 3)``."""
        return self._skin(None, global_rotations, global_positions)

    def pose_rows(self, index: Tensor, global_rotations: Tensor, global_positions: Tensor) -> Tensor:
        """The rows ``index (N,)`` of :meth:`pose_vertices`, ``(..., N, 3)``, computed the same way (bit-identical),
        without posing the other vertices."""
        return self._skin(index, global_rotations, global_positions)

    def _skin(self, index: Tensor | None, global_rotations: Tensor, global_positions: Tensor) -> Tensor:
        """Posed rows ``index (N,)`` (None: all) ``(..., N, 3)``: over each vertex's own influences (compiled) when
        no gradient is wanted on the CPU, else the dense differentiable form; either way each vertex's position
        depends on its own row only, so any subset is bit-identical to the same rows of the whole."""
        rest_rot, rest_pos = self.skeleton.rest_global()
        mats = kinematics.skinning_matrices(rest_rot, rest_pos, global_rotations, global_positions)
        rows = slice(None) if index is None else index
        if _differentiable(self.vertices, mats):
            return kinematics.linear_blend_skinning(self.vertices[rows], self.dense_weights()[rows], mats)
        flat = mats.reshape(-1, *mats.shape[-3:])
        posed = sparse_skinning(self.vertices[rows], self.skin_joints[rows], self.skin_weights[rows], flat)
        return posed.reshape(*mats.shape[:-3], *posed.shape[1:])

    def pose_vertex_subset(self, index: Tensor, global_rotations: Tensor, global_positions: Tensor,
                           chunk: int | None = None) -> Tensor:  # fmt: skip
        """Posed positions ``(F, N, 3)`` of the vertices ``index (N,)`` only, the same rows as :meth:`pose_vertices`,
        from world joint transforms ``(F, J, 4)`` and ``(F, J, 3)``, ``chunk`` frames at a time (default: as many
        as keep a chunk's posed float32 positions within :data:`kinematics.SKINNING_CHUNK_BYTES`)."""
        out = list(self._subset_chunks(index, global_rotations, global_positions, chunk))
        return torch.cat(out) if out else self.vertices.new_zeros(0, len(index), 3)

    def lowest_heights(self, index: Tensor, global_rotations: Tensor, global_positions: Tensor,
                       chunk: int | None = None) -> Tensor:  # fmt: skip
        """``(F,)`` the height of the lowest of the vertices ``index (N,)`` on each frame: :meth:`pose_vertex_subset`
        reduced chunk by chunk, so the posed frames are never all held at once."""
        out = [c[..., 1].amin(-1) for c in self._subset_chunks(index, global_rotations, global_positions, chunk)]
        return torch.cat(out) if out else self.vertices.new_zeros(0)

    def _subset_chunks(self, index: Tensor, global_rotations: Tensor, global_positions: Tensor,
                       chunk: int | None) -> Iterator[Tensor]:  # fmt: skip
        """:meth:`pose_vertex_subset`, one ``(f, N, 3)`` chunk of frames after another."""
        step = chunk or max(1, kinematics.SKINNING_CHUNK_BYTES // max(1, 12 * len(index)))
        for s in range(0, global_rotations.shape[0], step):
            yield self._skin(index, global_rotations[s : s + step], global_positions[s : s + step])

    def vertex_normals(self) -> Tensor:
        """Area-weighted unit vertex normals ``(V, 3)`` of the rest mesh."""
        tri = self.vertices[self.faces]
        n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
        out = torch.zeros_like(self.vertices)
        for k in range(3):
            out.index_add_(0, self.faces[:, k], n)
        return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _differentiable(*tensors: Tensor) -> bool:
    """Whether posing must keep gradients or stay off the CPU (then the dense torch form is used)."""
    wants_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    return wants_grad or any(t.device.type != "cpu" for t in tensors)
