"""Body parts of a skinned character: one segment per mapped canonical joint, vertex groups, the six clusters.

Every skeleton joint is assigned to the segment of its nearest mapped canonical ancestor (itself when mapped):
twist bones follow their limb, fingers their hand, face bones the head, joints above the hips the hips. A
segment's skinning weight of a vertex is the sum of the weights of the joints assigned to it, so the parts
work the same on a 22-joint Mixamo rig and on a 100-joint rig with fingers and twist bones.

- ``group(name)``: vertices whose segment weight is at least 0.5 (paper 1, section 3.4) and the triangles
  made only of them; the hand groups drive self-contact detection.
- ``vertex_part``: the dominant segment of each vertex (every vertex in exactly one part); the closed part
  meshes of the signed-distance fields and the penetration queries use this partition.
- clusters (paper 2, section 4): head, torso, left/right arm, left/right leg. The shoulders (clavicles) are in
  the torso cluster, so an arm cluster is upper arm, forearm and hand.
- masks: pairs never tested for collision: a segment with itself, parent/child segments, segments of the
  same cluster; paper 2's collision matrix additionally ignores upper arm against chest (section 7.1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from retarget_core.canonical import CANONICAL_JOINTS, JointMapping
from retarget_core.character import Character

CLUSTERS: tuple[str, ...] = ("head", "torso", "left_arm", "right_arm", "left_leg", "right_leg")

CLUSTER_OF: dict[str, str] = {
    "Hips": "torso", "Spine": "torso", "Spine1": "torso", "Spine2": "torso",
    "LeftShoulder": "torso", "RightShoulder": "torso",
    "Neck": "head", "Head": "head",
    "LeftArm": "left_arm", "LeftForeArm": "left_arm", "LeftHand": "left_arm",
    "RightArm": "right_arm", "RightForeArm": "right_arm", "RightHand": "right_arm",
    "LeftUpLeg": "left_leg", "LeftLeg": "left_leg", "LeftFoot": "left_leg", "LeftToeBase": "left_leg",
    "RightUpLeg": "right_leg", "RightLeg": "right_leg", "RightFoot": "right_leg", "RightToeBase": "right_leg",
}  # fmt: skip

HAND_SEGMENTS: tuple[str, ...] = ("LeftHand", "RightHand")

# Paper 2, section 7.1: M_c, M_i and M_o are measured on the end effectors of the limbs and their parents.
END_EFFECTOR_SEGMENTS: dict[str, tuple[str, ...]] = {
    "left_arm": ("LeftHand", "LeftForeArm"),
    "right_arm": ("RightHand", "RightForeArm"),
    "left_leg": ("LeftFoot", "LeftToeBase", "LeftLeg"),
    "right_leg": ("RightFoot", "RightToeBase", "RightLeg"),
}

# Paper 2, section 7.1: "collisions between the upper arm and chest segments ... are also ignored".
ARM_CHEST_PAIRS: tuple[tuple[str, str], ...] = (
    ("LeftArm", "Spine2"), ("LeftArm", "Spine1"), ("RightArm", "Spine2"), ("RightArm", "Spine1"),
)  # fmt: skip

GROUP_THRESHOLD = 0.5


def segment_of_joints(num_joints: int, parents: list[int], mapping: JointMapping) -> list[str | None]:
    """For every skeleton joint, the canonical segment it belongs to: its own canonical name when mapped, else
    that of its nearest mapped ancestor; joints with no mapped ancestor (above the hips) go to ``Hips``."""
    own = {j: name for name, j in mapping.joints.items()}
    out: list[str | None] = []
    for j in range(num_joints):
        k = j
        while k >= 0 and k not in own:
            k = parents[k]
        out.append(own[k] if k >= 0 else ("Hips" if "Hips" in mapping.joints else None))
    return out


@dataclass
class BodyParts:
    """Segments of one character (in the order of :data:`CANONICAL_JOINTS`, mapped ones only).

    names: ``(S,)`` canonical names of the segments.
    joints: ``(S,)`` skeleton joint index of each segment's canonical joint (its rigid frame).
    parent: ``(S,)`` parent segment (nearest mapped canonical ancestor in the skeleton) or ``-1``.
    cluster: ``(S,)`` index into :data:`CLUSTERS`.
    weights: ``(V, S)`` segment skinning weights (sum of the weights of the joints assigned to the segment).
    vertex_part: ``(V,)`` dominant segment of each vertex.
    face_part: ``(T,)`` dominant segment of each triangle (largest summed weight of its three vertices).
    faces: ``(T, 3)`` the body's triangles: the character's, less those of accessory meshes
        (:attr:`Character.meshes`); the part volumes (SDF grids, hand distances) are made of these.
    body: ``(V,)`` bool, False on accessory vertices: they keep a dominant segment (``vertex_part``) but belong
        to no group and no part's vertex list, so no measure tests them; None: every vertex is body.
    """

    names: list[str]
    joints: list[int]
    parent: list[int]
    cluster: list[int]
    weights: Tensor
    vertex_part: Tensor
    face_part: Tensor
    faces: Tensor
    body: Tensor | None = None
    _index: dict[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._index = {n: i for i, n in enumerate(self.names)}

    @property
    def num_parts(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """The segment index of canonical joint ``name`` (KeyError when not mapped)."""
        return self._index[name]

    def find(self, name: str) -> int | None:
        """The segment index of ``name`` or None."""
        return self._index.get(name)

    def group(self, name: str, threshold: float = GROUP_THRESHOLD) -> Tensor:
        """Body vertex indices ``(N,)`` whose weight for segment ``name`` is at least ``threshold``."""
        return torch.nonzero(self._body_only(self.weights[:, self.index(name)] >= threshold)).flatten()

    def group_faces(self, name: str, threshold: float = GROUP_THRESHOLD) -> Tensor:
        """Triangles ``(M, 3)`` whose three vertices are all in :meth:`group`."""
        inside = self._body_only(self.weights[:, self.index(name)] >= threshold)
        return self.faces[inside[self.faces].all(dim=1)]

    def part_vertices(self, s: int) -> Tensor:
        """Body vertex indices ``(N,)`` whose dominant segment is ``s``."""
        return torch.nonzero(self._body_only(self.vertex_part == s)).flatten()

    def _body_only(self, mask: Tensor) -> Tensor:
        if self.body is None:
            return mask
        if self.body.shape != mask.shape:
            raise ValueError(f"BodyParts.body has {self.body.shape[0]} vertices, the parts {mask.shape[0]}: a vertex "
                             "subset of the parts must take the same subset of body")  # fmt: skip
        return mask & self.body

    @property
    def body_count(self) -> int:
        """Number of body vertices (all vertices when the character has no accessory mesh)."""
        return int(self.vertex_part.shape[0]) if self.body is None else int(self.body.sum())

    def adjacency(self) -> Tensor:
        """``(S, S)`` bool: parent/child segment pairs (symmetric)."""
        adj = torch.zeros(self.num_parts, self.num_parts, dtype=torch.bool)
        for s, p in enumerate(self.parent):
            if p >= 0:
                adj[s, p] = adj[p, s] = True
        return adj

    def same_cluster(self) -> Tensor:
        """``(S, S)`` bool: both segments in the same cluster."""
        c = torch.tensor(self.cluster)
        return c[:, None] == c[None, :]

    def collision_mask(self, ignore_arm_chest: bool = False) -> Tensor:
        """``(S, S)`` bool, True where a pair is tested: different, non-adjacent segments of different clusters
        (paper 2's masking matrix Omega); ``ignore_arm_chest`` also drops upper arm against chest."""
        allowed = ~(self.adjacency() | self.same_cluster())
        allowed.fill_diagonal_(False)
        if ignore_arm_chest:
            for a, b in ARM_CHEST_PAIRS:
                i, j = self.find(a), self.find(b)
                if i is not None and j is not None:
                    allowed[i, j] = allowed[j, i] = False
        return allowed

    def cluster_members(self) -> dict[str, list[int]]:
        """Cluster name -> segment indices."""
        out: dict[str, list[int]] = {c: [] for c in CLUSTERS}
        for s, c in enumerate(self.cluster):
            out[CLUSTERS[c]].append(s)
        return out


def body_parts(character: Character, mapping: JointMapping) -> BodyParts:
    """The segments, groups and clusters of ``character`` whose skeleton is mapped by ``mapping``."""
    sk = character.skeleton
    names = [c for c in CANONICAL_JOINTS if c in mapping.joints]
    if not names:
        raise ValueError("the joint mapping maps no canonical joint")
    index = {n: i for i, n in enumerate(names)}
    seg_of_joint = segment_of_joints(sk.num_joints, sk.parents, mapping)
    joint_to_seg = torch.tensor([index[s] if s is not None else -1 for s in seg_of_joint], dtype=torch.long)
    dense = character.dense_weights()  # (V, J)
    weights = torch.zeros(dense.shape[0], len(names), dtype=dense.dtype)
    keep = joint_to_seg >= 0
    weights.index_add_(1, joint_to_seg[keep], dense[:, keep])
    vertex_part = weights.argmax(dim=1)
    faces = character.body_faces()
    face_w = weights[faces].sum(dim=1)  # (T, S)
    face_part = face_w.argmax(dim=1)
    parent = []
    for n in names:
        j = sk.parents[mapping.joints[n]]
        while j >= 0 and seg_of_joint[j] is None:
            j = sk.parents[j]
        p = index[seg_of_joint[j]] if j >= 0 and seg_of_joint[j] is not None else -1  # type: ignore[index]
        parent.append(p if p != index[n] else -1)
    cluster = [CLUSTERS.index(CLUSTER_OF[n]) for n in names]
    body = character.body_vertices if character.has_accessories else None
    return BodyParts(names, [mapping.joints[n] for n in names], parent, cluster, weights, vertex_part, face_part, faces,
                     body)  # fmt: skip


def mapping_by_name(names: list[str]) -> JointMapping:
    """A joint mapping that maps canonical joints present under exactly their canonical name (Mixamo rigs
    without prefix, such as the shared MakeHuman bodies)."""
    joints = {c: names.index(c) for c in CANONICAL_JOINTS if c in names}
    return JointMapping(joints, {c: 1.0 for c in joints}, {c: "name" for c in joints})


__all__ = [
    "ARM_CHEST_PAIRS",
    "CLUSTERS",
    "CLUSTER_OF",
    "END_EFFECTOR_SEGMENTS",
    "HAND_SEGMENTS",
    "BodyParts",
    "body_parts",
    "mapping_by_name",
    "segment_of_joints",
]
