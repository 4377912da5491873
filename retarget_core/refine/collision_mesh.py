"""Arm and head vertices inside the posed torso mesh, as the judge sees them (closed parts, winding numbers),
and a differentiable depth for them: the collision stage's complement to the rigid part SDFs.

Why: the part SDFs are rigid grids in each segment's rest frame. Near the armpit the torso's skin is skinned
partly to the arm (weights of Spine1, Spine2, Shoulder and Arm mixed), so when an arm hangs at the side of a
bulky body the posed torso surface bulges out with it and holds upper-arm vertices 1-3 cm deep, 7-14 cm from
any part seam, while the rigid Spine grids see them outside (on bulky, heavy and tall bodies, most of the frames
the judge counts deeper than 1 cm after the stage without this test). The chin meets the chest the same way: the
upper chest is skinned partly to the neck, and the judge counts any head vertex inside the torso (head %v). Here
the posed closed parts of :mod:`retarget_core.metrics.acceptance_body` are tested directly (closest triangle and
winding number through a tree refit per frame, :mod:`retarget_core.geometry.triangle_bvh`), and each (frame,
tester vertex, triangle) found is given the plane distance to its posed triangle, which the optimiser can
differentiate.

Lengths in metres on the body's own scale unless the name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.geometry.bvh_kernels import rows_bounds, rows_in_boxes
from retarget_core.geometry.triangle_bvh import (
    PosedBoxes,
    TriangleBVH,
    build_bvh,
    closest_triangles,
    refit,
    winding_numbers,
)
from retarget_core.metrics.acceptance_body import PARTS, AcceptanceBody, acceptance_body

MESH_TARGETS: dict[str, tuple[str, ...]] = {"left_arm": ("torso",), "right_arm": ("torso",), "head": ("torso",)}
"""Tester part -> parts whose posed meshes its vertices are tested against (the rigid SDFs miss these)."""

SKIN_DRAG_WEIGHT = 0.01  # torso vertices with more of a tester's skin weight than this move with it (the bulge)
TESTER_REACH_M = 0.20  # tester vertices within this (rest, at 1.80 m) of such torso vertices are tested
CHUNK_BUDGET_BYTES = 160 * 2**20  # posed frames and part-tree boxes held at once: 32 frames on MakeHuman bodies


@dataclass
class MeshPairs:
    """(frame, tester vertex, triangle) found inside or near a posed part, ``(N,)`` each.

    frame: index into the frames measured; vertex: body vertex; tri: ``(N, 3)`` body vertices of the closest
    triangle of the part; sign: +-1 with ``sign * (x - a) . n`` the signed distance (positive outside) for the
    triangle's unit normal ``n`` and first vertex ``a``; depth: the measured depth (> 0 inside, < 0 outside)."""

    frame: Tensor
    vertex: Tensor
    tri: Tensor
    sign: Tensor
    depth: Tensor

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])

    def max_depth(self, frames: int) -> Tensor:
        """``(frames,)`` deepest inside depth per frame (0 where none)."""
        out = torch.zeros(frames, dtype=self.depth.dtype)
        return out.scatter_reduce(0, self.frame, self.depth.clamp_min(0.0), "amax", include_self=True)

    def select(self, keep: Tensor) -> MeshPairs:
        return MeshPairs(self.frame[keep], self.vertex[keep], self.tri[keep], self.sign[keep], self.depth[keep])

    @staticmethod
    def concat(parts: list[MeshPairs]) -> MeshPairs:
        """The pairs of ``parts``, one after the other (none when empty)."""
        if not parts:
            e = torch.zeros(0, dtype=torch.long)
            return MeshPairs(e, e, torch.zeros(0, 3, dtype=torch.long), torch.zeros(0), torch.zeros(0))
        return MeshPairs(*(torch.cat([getattr(m, k) for m in parts]) for k in ("frame", "vertex", "tri", "sign", "depth")))

    def union(self, other: MeshPairs, num_vertices: int) -> MeshPairs:
        """These pairs and ``other``'s, one per (frame, vertex): ``other``'s where both have one."""
        both = MeshPairs.concat([other, self])
        key = both.frame * num_vertices + both.vertex
        _, inv = torch.unique(key, return_inverse=True)
        first = torch.full((int(inv.max()) + 1 if len(inv) else 0,), len(key), dtype=torch.long)
        first = first.scatter_reduce(0, inv, torch.arange(len(key)), "amin")
        return both.select(first)


@dataclass
class MeshSetup:
    """Per body: the judge's parts (``body``) and, per tester part of :data:`MESH_TARGETS`, the tested vertices
    ``testers[part] (T,)`` (counted by the judge and within reach of the dragged skin), the dragged torso
    vertices ``dragged[part] (D,)`` (skinned partly to that tester part) and each target part's tree."""

    body: AcceptanceBody
    testers: dict[str, np.ndarray]
    dragged: dict[str, np.ndarray]
    trees: dict[str, TriangleBVH]  # target part -> its closed mesh's tree (rest pose, refit per frame)

    def read_vertices(self) -> np.ndarray:
        """Sorted body vertices :func:`find_mesh_pairs` reads: testers, dragged skin and the target parts'."""
        targets = [part.vertices for t in dict.fromkeys(t for ts in MESH_TARGETS.values() for t in ts)
                   if (part := self.body.part(t)) is not None]  # fmt: skip
        return np.unique(np.concatenate([*self.testers.values(), *self.dragged.values(), *targets]).astype(np.int64))


def mesh_setup(character: Character, mapping: JointMapping) -> MeshSetup:
    """The judge's body and the vertices :func:`find_mesh_pairs` tests (a second or two the first time a body
    is seen in a process: the judge's seam band)."""
    from retarget_core.body_parts import CLUSTERS, body_parts

    body = acceptance_body(character, mapping)
    parts = body_parts(character, mapping)
    rest = character.vertices.detach().double().numpy()
    reach = TESTER_REACH_M * character.height / 1.80
    seg_cluster = np.asarray(parts.cluster)
    w = parts.weights.numpy()
    torso = body.part_of_vertex == PARTS.index("torso")
    testers_: dict[str, np.ndarray] = {}
    dragged: dict[str, np.ndarray] = {}
    for p in MESH_TARGETS:
        own_w = w[:, seg_cluster == CLUSTERS.index(p)].sum(1)
        d = np.nonzero(torso & (own_w > SKIN_DRAG_WEIGHT))[0]
        cand = np.nonzero((body.part_of_vertex == PARTS.index(p)) & ~body.seam)[0]
        if len(d) and len(cand):
            gap = np.min(np.linalg.norm(rest[cand, None] - rest[None, d[:: max(1, len(d) // 64)]], axis=-1), axis=1)
            cand = cand[gap < reach]
        testers_[p], dragged[p] = cand, d
    trees = {t: build_bvh(part.posed(rest), part.faces) for t in dict.fromkeys(t for ts in MESH_TARGETS.values() for t in ts)
             if (part := body.part(t)) is not None}  # fmt: skip
    return MeshSetup(body, testers_, dragged, trees)


def part_mask(setup: MeshSetup, part: str) -> Tensor:
    """``(V,)`` bool: the body vertices the judge counts in ``part`` (one of :data:`PARTS`)."""
    return torch.from_numpy(setup.body.part_of_vertex == PARTS.index(part))


def find_mesh_pairs(setup: MeshSetup, posed: np.ndarray, near: float, reach: float) -> MeshPairs:
    """Pairs of posed frames ``posed (n, V, 3)``: tester vertices within ``reach`` of the dragged skin's posed
    box that are inside a target part, or outside within ``near`` of it; closest points on a cap fan are left
    out (the judge does). All frames at once through each part's refit tree."""
    return MeshPairs.concat([_part_pairs(setup, t_name, posed, near, reach) for t_name in setup.trees])


def _part_pairs(setup: MeshSetup, t_name: str, posed: np.ndarray, near: float, reach: float) -> MeshPairs:
    """:func:`find_mesh_pairs` against one target part ``t_name``."""
    part, tree = setup.body.part(t_name), setup.trees[t_name]
    assert part is not None
    frame, vertex = _queries(setup, t_name, posed, reach)
    if len(frame) == 0:
        return MeshPairs.concat([])
    local = torch.from_numpy(part.posed(posed))  # (n, N + L, 3)
    boxes = refit(tree, local)
    q = torch.from_numpy(posed[frame.numpy(), vertex.numpy()])
    inside = _inside(tree, boxes, frame, q)
    # inside: the depth up to reach (deeper: the rigid SDFs see it); outside: only whether within near
    d, face = closest_triangles(tree, boxes, frame, q, torch.where(inside, reach, near).to(q.dtype))
    close = torch.nonzero(face >= 0).flatten()
    keep = close[(inside[close] | (d[close] < near)) & ~torch.from_numpy(part.is_cap)[face[close]]]
    tri_local = tree.faces[face[keep]]
    a, b, c = (local[frame[keep], tri_local[:, k]] for k in range(3))
    s0 = plane_distance(torch.ones(len(keep), dtype=q.dtype), q[keep], a, b, c)
    depth = torch.where(inside[keep], d[keep], -d[keep])
    sign = torch.where(-depth * s0 >= 0.0, 1.0, -1.0)
    return MeshPairs(frame[keep], vertex[keep], torch.from_numpy(part.vertices)[tri_local], sign.float(), depth.float())


def _inside(tree: TriangleBVH, boxes: PosedBoxes, frame: Tensor, q: Tensor) -> Tensor:
    """``(Q,)`` whether each of ``q (Q, 3)`` is inside the closed part in posed frame ``frame (Q,)``: winding
    numbers for the points within the part's box (the others are outside)."""
    lo, hi = boxes.lo[frame, 0], boxes.hi[frame, 0]  # the root's box per query
    in_box = torch.nonzero(((q >= lo) & (q <= hi)).all(dim=-1)).flatten()
    inside = torch.zeros(len(q), dtype=torch.bool)
    inside[in_box] = winding_numbers(tree, boxes, frame[in_box], q[in_box]).abs() > 0.5
    return inside


def _queries(setup: MeshSetup, t_name: str, posed: np.ndarray, reach: float) -> tuple[Tensor, Tensor]:
    """``(Q,)`` frames and tester vertices tested against part ``t_name`` in ``posed (n, V, 3)``: each tester part's
    vertices inside its posed dragged skin's box grown by ``reach``."""
    frames, vertices = [torch.zeros(0, dtype=torch.long)], [torch.zeros(0, dtype=torch.long)]
    for tester, targets in MESH_TARGETS.items():
        cand, drag = setup.testers[tester], setup.dragged[tester]
        if t_name not in targets or len(cand) == 0 or len(drag) == 0:
            continue
        lo, hi = rows_bounds(posed, drag)  # (n, 3)
        f, k = rows_in_boxes(posed, cand, lo - reach, hi + reach)
        frames.append(torch.from_numpy(f).long())
        vertices.append(torch.from_numpy(cand[k]).long())
    return torch.cat(frames), torch.cat(vertices)


def mesh_pairs_of_motion(character: Character, setup: MeshSetup, rotations: Tensor, translations: Tensor,
                         frames: Tensor, near: float, chunk: int = 32) -> MeshPairs:  # fmt: skip
    """:func:`find_mesh_pairs` at clip ``frames (n,)`` of local ``rotations (F, J, 4)`` / ``translations``, at most
    ``chunk`` frames at a time (fewer where a chunk's posed vertices and largest part tree's boxes would pass
    :data:`CHUNK_BUDGET_BYTES`); the pairs' ``frame`` indexes ``frames``."""
    from retarget_core import kinematics

    out: list[MeshPairs] = []
    read = setup.read_vertices()  # only these are posed: the rest of the array stays zero, unread
    per_frame = 24 * character.num_vertices + max((t.box_bytes() for t in setup.trees.values()), default=0)
    chunk = max(1, min(chunk, CHUNK_BUDGET_BYTES // per_frame))
    with torch.no_grad():
        for s in range(0, len(frames), chunk):
            fr = frames[s : s + chunk]
            grot, gpos = kinematics.forward_kinematics(character.skeleton.parents, rotations[fr], translations[fr])
            posed = np.zeros((len(fr), character.num_vertices, 3))
            posed[:, read] = character.pose_rows(torch.from_numpy(read), grot, gpos).double().numpy()
            mp = find_mesh_pairs(setup, posed, near, 0.05 * character.height / 1.80)
            mp.frame += s
            out.append(mp)
    return MeshPairs.concat(out)


@dataclass
class MeshTerms:
    """Mesh pairs as indices into a point set: ``frame (N,)`` optimised frame, ``point (N,)``, ``tri (N, 3)``,
    ``sign (N,)``."""

    frame: Tensor
    point: Tensor
    tri: Tensor
    sign: Tensor

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])


def plane_distance(sign: Tensor, x: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """``(N,)`` signed distance (m, positive outside) of points ``x (N, 3)`` to the planes of triangles ``a, b, c
    (N, 3)``, oriented by ``sign (N,)``."""
    n = torch.cross(b - a, c - a, dim=-1)
    n = n / (n.norm(dim=-1, keepdim=True) + 1e-12)
    return sign * ((x - a) * n).sum(-1)


def mesh_rows(terms: MeshTerms, posed: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each pair's posed point and triangle corners ``(N, 3)`` each, from ``posed (Fa, P, 3)``."""
    flat = posed.reshape(-1, 3)
    base = terms.frame * posed.shape[1]
    x = flat.index_select(0, base + terms.point)
    a, b, c = (flat.index_select(0, base + terms.tri[:, k]) for k in range(3))
    return x, a, b, c


def mesh_signed_distance(terms: MeshTerms, posed: Tensor) -> Tensor:
    """``(N,)`` signed distance (m, positive outside) of each pair's posed point to its posed triangle's plane;
    ``posed (Fa, P, 3)``."""
    return plane_distance(terms.sign, *mesh_rows(terms, posed))


def mesh_energy_rows(terms: MeshTerms, x: Tensor, a: Tensor, b: Tensor, c: Tensor, scale: float,
                     clearance: float) -> Tensor:  # fmt: skip
    """Sum of ``relu(clearance - d)^2`` (cm^2 at 1.80 m) over the pairs (a scalar), posed points ``x (N, 3)`` and
    triangles ``a, b, c (N, 3)``."""
    d = plane_distance(terms.sign, x, a, b, c)
    return ((clearance - d).clamp_min(0.0) * (100.0 * scale)).pow(2).sum()


def mesh_energy(terms: MeshTerms, posed: Tensor, scale: float, clearance: float) -> Tensor:
    """:func:`mesh_energy_rows` on ``posed (Fa, P, 3)``."""
    if terms.count == 0:
        return posed.new_zeros(())
    return mesh_energy_rows(terms, *mesh_rows(terms, posed), scale, clearance)


__all__ = [
    "MESH_TARGETS",
    "MeshPairs",
    "MeshTerms",
    "find_mesh_pairs",
    "MeshSetup",
    "mesh_setup",
    "mesh_energy",
    "mesh_energy_rows",
    "plane_distance",
    "mesh_pairs_of_motion",
    "mesh_signed_distance",
    "part_mask",
]
