"""What the acceptance judge needs to know about one body, computed once per body (rest pose only).

Definitions are those of ``../shared/ACCEPTANCE.md``: every vertex belongs to the canonical joint with the
largest summed skin weight (:func:`retarget_core.body_parts.body_parts`), grouped into six parts: head (Neck,
Head), torso (Hips, Spine*, both Shoulders), each arm (Arm, ForeArm, Hand), each leg (UpLeg, Leg, Foot,
ToeBase). Hand vertices are those whose dominant joint is a Hand; foot vertices those whose dominant joint is a
Foot or ToeBase.

Each part is closed into a volume: its triangles (a triangle belongs to the part of its dominant joint, largest
summed weight of its three vertices, so the parts tile the surface) plus a fan over every open boundary loop
(:func:`retarget_core.energy.mesh_distance.cap_boundary_loops`). A posed part is the posed vertices plus, per
cap, the mean of the posed loop vertices as the fan's centre.

Seam band: vertices within ``SEAM_BAND_M`` (3 cm at 1.80 m) of a part boundary along the rest mesh surface are
not counted as penetrating (armpit, crotch, neck folds). Distances are exact polyhedral geodesics (libigl's
``exact_geodesic``) from the boundary vertices (every vertex with a neighbour in another part). Approximation:
the boundary is taken at those vertices, not at the mid-edges between parts, so the band is up to half an edge
wider than 3 cm on the inner side.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from retarget_core.body_parts import CLUSTERS, body_parts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.energy.mesh_distance import cap_boundary_loops
from retarget_core.energy.sdf import vertex_clusters

REFERENCE_HEIGHT_M = 1.80
SEAM_BAND_M = 0.03  # ACCEPTANCE.md: "within 3 cm, along the rest mesh surface, of a part boundary"
CLUSTER_M = 0.04  # rest-pose voxel of the vertex clusters used for culling (about 15 vertices each)
BODY_CACHE_SIZE = 16  # bodies kept in memory (about 2 MB each)

PARTS: tuple[str, ...] = CLUSTERS  # head, torso, left_arm, right_arm, left_leg, right_leg
HANDS: tuple[str, ...] = ("left", "right")
CONTACT_PARTS: tuple[str, ...] = ("head", "torso", "other_arm", "legs")

# ACCEPTANCE.md: an arm vertex is tested against torso, head, the other arm and both legs; a leg vertex
# against the other leg and both arms. The head against the torso is measured apart.
LIMB_TESTS: dict[str, tuple[str, ...]] = {
    "left_arm": ("torso", "head", "right_arm", "left_leg", "right_leg"),
    "right_arm": ("torso", "head", "left_arm", "left_leg", "right_leg"),
    "left_leg": ("right_leg", "left_arm", "right_arm"),
    "right_leg": ("left_leg", "left_arm", "right_arm"),
}
HEAD_TESTS: dict[str, tuple[str, ...]] = {"head": ("torso",)}


def contact_targets(hand: str) -> dict[str, tuple[str, ...]]:
    """For a hand (``left``/``right``): contact part name -> the parts it is made of."""
    other = "right_arm" if hand == "left" else "left_arm"
    return {"head": ("head",), "torso": ("torso",), "other_arm": (other,), "legs": ("left_leg", "right_leg")}


@dataclass
class ClosedPart:
    """One part closed into a volume.

    vertices: ``(N,)`` body vertex indices used by the part's own triangles (local vertices ``0..N-1``).
    faces: ``(T, 3)`` local indices; cap centres are local vertices ``N..N+L-1``.
    cap_loops: ``L`` arrays of body vertex indices; centre ``k`` is the mean of loop ``k``'s posed vertices.
    is_cap: ``(T,)`` True for the fan triangles.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    cap_loops: list[np.ndarray]
    is_cap: np.ndarray

    def posed(self, posed_vertices: np.ndarray, frames: np.ndarray | None = None) -> np.ndarray:
        """Local vertex positions ``(..., N + L, 3)`` from the body's posed vertices ``(..., V, 3)``; ``frames
        (k,)``: of those rows of posed vertices ``(F, V, 3)`` only, ``(k, N + L, 3)`` (the others' not copied)."""

        def rows(idx: np.ndarray) -> np.ndarray:
            return posed_vertices[..., idx, :] if frames is None else posed_vertices[frames[:, None], idx]

        own = rows(self.vertices)
        if not self.cap_loops:
            return own
        centres = np.stack([rows(loop).mean(axis=-2) for loop in self.cap_loops], axis=-2)
        return np.concatenate([own, centres], axis=-2)


@dataclass
class AcceptanceBody:
    """The judge's view of one body's rest pose.

    part_of_vertex: ``(V,)`` index into :data:`PARTS`.
    hand_vertices: hand -> ``(H,)`` vertex indices; foot_vertices: side -> ``(K,)`` vertex indices.
    seam: ``(V,)`` True within the seam band of a part boundary.
    parts: one :class:`ClosedPart` per entry of :data:`PARTS` (None when a part has no triangles).
    cluster_members: ``(C, K)`` vertex indices of small clusters of nearby vertices of one joint each, padded
        with -1 (rest-pose voxels of ``CLUSTER_M``), used to cull queries; every vertex outside the seam band and
        every hand vertex is in one cluster; cluster_part ``(C,)`` their part;
        cluster_hand ``(C,)`` index into :data:`HANDS` of hand clusters, -1 for the others;
        hand_of_vertex ``(V,)`` the same per vertex.
    height: rest mesh height (m); scale_to_180: factor to a 1.80 m character.
    """

    height: float
    part_of_vertex: np.ndarray
    hand_vertices: dict[str, np.ndarray]
    foot_vertices: dict[str, np.ndarray]
    seam: np.ndarray
    seam_distance: np.ndarray
    parts: list[ClosedPart | None]
    cluster_members: np.ndarray
    cluster_part: np.ndarray
    cluster_hand: np.ndarray
    hand_of_vertex: np.ndarray

    @property
    def scale_to_180(self) -> float:
        return REFERENCE_HEIGHT_M / self.height

    def part(self, name: str) -> ClosedPart | None:
        return self.parts[PARTS.index(name)]

    def part_vertices(self, name: str) -> np.ndarray:
        """``(N,)`` vertices whose part is ``name``."""
        return np.nonzero(self.part_of_vertex == PARTS.index(name))[0]


def _close_part(name: str, vertices: np.ndarray, faces: np.ndarray) -> ClosedPart:
    """The part made of ``faces`` (body vertex indices) with a fan over every boundary loop."""
    cv, cf = cap_boundary_loops(vertices, faces)
    n_own = len(faces)
    used = np.unique(faces)
    local = np.full(len(cv), -1, dtype=np.int64)
    local[used] = np.arange(len(used))
    caps = cf[n_own:]
    centres = np.unique(caps[:, 2]) if len(caps) else np.zeros(0, dtype=np.int64)
    loops = []
    for k, c in enumerate(centres):
        loops.append(np.unique(caps[caps[:, 2] == c][:, :2]))
        local[c] = len(used) + k
    return ClosedPart(name, used, local[cf], loops, np.arange(len(cf)) >= n_own)


def seam_distances(vertices: np.ndarray, faces: np.ndarray, part_of_vertex: np.ndarray) -> np.ndarray:
    """Geodesic distance ``(V,)`` along the surface from every vertex to the nearest part-boundary vertex."""
    import igl

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    cross = part_of_vertex[e[:, 0]] != part_of_vertex[e[:, 1]]
    sources = np.unique(e[cross].ravel())
    if len(sources) == 0:
        return np.full(len(vertices), np.inf)
    targets = np.arange(len(vertices), dtype=np.int64)
    return np.asarray(igl.exact_geodesic(vertices, faces, sources.astype(np.int64), np.zeros(0, np.int64), targets))


def build_acceptance_body(character: Character, mapping: JointMapping) -> AcceptanceBody:
    """The parts, closed volumes, hands, feet and seam band of ``character`` (about a second for 13k vertices)."""
    parts = body_parts(character, mapping)
    cluster = np.asarray(parts.cluster, dtype=np.int64)
    vertex_seg = parts.vertex_part.numpy()
    part_of_vertex = cluster[vertex_seg]
    face_part = cluster[parts.face_part.numpy()]
    verts = character.vertices.detach().double().numpy()
    faces = parts.faces.numpy().astype(np.int64)  # the body meshes' triangles (docs/meshes.md)
    body = np.ones(len(verts), dtype=bool) if parts.body is None else parts.body.numpy()
    s = character.height / REFERENCE_HEIGHT_M
    closed: list[ClosedPart | None] = []
    for p, name in enumerate(PARTS):
        pf = faces[face_part == p]
        closed.append(_close_part(name, verts, pf) if len(pf) else None)

    def seg_vertices(names: tuple[str, ...]) -> np.ndarray:
        found = [parts.find(n) for n in names]
        idx = [i for i in found if i is not None]
        return np.nonzero(np.isin(vertex_seg, idx) & body)[0]

    hands = {"left": seg_vertices(("LeftHand",)), "right": seg_vertices(("RightHand",))}
    feet = {"left": seg_vertices(("LeftFoot", "LeftToeBase")), "right": seg_vertices(("RightFoot", "RightToeBase"))}
    height = character.height
    dist = seam_distances(verts, faces, part_of_vertex)
    seam = dist < SEAM_BAND_M * s
    hand_of_vertex = np.full(len(verts), -1, dtype=np.int64)
    for k, h in enumerate(HANDS):
        hand_of_vertex[hands[h]] = k
    # Seam-band vertices never count as penetrating: only the others (and the hands, for contacts) are queried.
    queried = np.nonzero((~seam | (hand_of_vertex >= 0)) & body)[0]
    clusters = vertex_clusters(character.vertices.detach().float()[queried], parts.vertex_part[queried], CLUSTER_M * s)
    members = clusters.members.numpy()
    members = np.where(members >= 0, queried[np.clip(members, 0, None)], -1)
    first = members[:, 0]
    return AcceptanceBody(
        height=height,
        part_of_vertex=part_of_vertex,
        hand_vertices=hands,
        foot_vertices=feet,
        seam=seam,
        seam_distance=dist,
        parts=closed,
        cluster_members=members,
        cluster_part=part_of_vertex[first],
        cluster_hand=hand_of_vertex[first],
        hand_of_vertex=hand_of_vertex,
    )


_CACHE: OrderedDict[str, AcceptanceBody] = OrderedDict()
T = TypeVar("T")


def body_key(character: Character, mapping: JointMapping) -> str:
    """A content key of a character and its mapping (rest mesh, faces, skin, skeleton, mapped joints)."""
    h = hashlib.sha1()
    for t in (character.vertices, character.faces, character.skin_joints, character.skin_weights,
              character.skeleton.rest_translations, character.skeleton.rest_rotations):  # fmt: skip
        h.update(t.detach().contiguous().cpu().numpy().tobytes())
    h.update(repr(sorted(mapping.joints.items())).encode())
    h.update(repr(list(character.skeleton.parents)).encode())
    return h.hexdigest()


def cached_per_body(cache: OrderedDict[str, T], character: Character, mapping: JointMapping,
                    build: Callable[[Character, JointMapping], T], size: int) -> T:  # fmt: skip
    """``build(character, mapping)``, kept in ``cache`` (least recently used first out, at most ``size``) by the
    character's content (:func:`body_key`)."""
    key = body_key(character, mapping)
    hit = cache.get(key)
    if hit is not None:
        cache.move_to_end(key)
        return hit
    cache[key] = built = build(character, mapping)
    while len(cache) > size:
        cache.popitem(last=False)
    return built


def acceptance_body(character: Character, mapping: JointMapping) -> AcceptanceBody:
    """:func:`build_acceptance_body`, cached in-process by the character's content."""
    return cached_per_body(_CACHE, character, mapping, build_acceptance_body, BODY_CACHE_SIZE)


__all__ = [
    "CONTACT_PARTS",
    "HANDS",
    "HEAD_TESTS",
    "LIMB_TESTS",
    "PARTS",
    "AcceptanceBody",
    "ClosedPart",
    "acceptance_body",
    "body_key",
    "cached_per_body",
    "build_acceptance_body",
    "contact_targets",
    "seam_distances",
]
