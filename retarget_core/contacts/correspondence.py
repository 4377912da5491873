"""Vertex correspondence between two skinned meshes of any topology (paper 1, section 3.4 and appendix F).

A vertex's feature is its skinning weights over the 22 canonical segments plus its offset from the joints that
move it, in the rest pose, nearest neighbour by KD-tree (scipy cKDTree). The paper uses "skinning weights and
offset from the parent joint"; we make the offset comparable across bodies and rest poses:

- the offset from segment ``j``'s joint is expressed in a frame attached to the bone (primary axis along the
  bone toward its child joint; secondary axis the body's forward +Z, or up +Y for feet and toes), so a T-pose
  and an A-pose body give the same coordinates;
- each axis is divided by the segment's size along it (bone length along the bone, the root mean square of the
  segment's vertices across it), so a skinny and a bulky forearm map surface to surface;
- the offsets from all segments are blended by the vertex's weights (continuous across joints).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, BodyParts, body_parts
from retarget_core.canonical import CANONICAL_JOINTS, CANONICAL_PARENT, JointMapping
from retarget_core.character import Character
from retarget_core.contacts.self_contact import SelfContacts

# The bone of a canonical joint points to the first mapped joint of this list; joints without one (hands, head,
# toes) use the direction from their parent.
BONE_CHILD: dict[str, tuple[str, ...]] = {
    "Hips": ("Spine", "Spine1", "Spine2", "Neck"), "Spine": ("Spine1", "Spine2", "Neck"),
    "Spine1": ("Spine2", "Neck"), "Spine2": ("Neck", "Head"), "Neck": ("Head",),
    "LeftShoulder": ("LeftArm",), "LeftArm": ("LeftForeArm",), "LeftForeArm": ("LeftHand",),
    "RightShoulder": ("RightArm",), "RightArm": ("RightForeArm",), "RightForeArm": ("RightHand",),
    "LeftUpLeg": ("LeftLeg",), "LeftLeg": ("LeftFoot",), "LeftFoot": ("LeftToeBase",),
    "RightUpLeg": ("RightLeg",), "RightLeg": ("RightFoot",), "RightFoot": ("RightToeBase",),
}  # fmt: skip
UP_SECONDARY = ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase")


@dataclass(frozen=True)
class CorrespondenceParams:
    """Relative weight of the two halves of the feature vector."""

    weight_scale: float = 1.0
    offset_scale: float = 0.5


def _frame(primary: Tensor, secondary: Tensor) -> Tensor:
    """Rotation ``(3, 3)`` whose columns are (primary, secondary made orthogonal, their cross product)."""
    a = primary / primary.norm().clamp_min(1e-12)
    b = secondary - (secondary @ a) * a
    if float(b.norm()) < 1e-6:
        b = torch.tensor([1.0, 0.0, 0.0], dtype=a.dtype) - a[0] * a
    b = b / b.norm().clamp_min(1e-12)
    return torch.stack([a, b, torch.cross(a, b, dim=0)], dim=1)


def correspondence_features(character: Character, mapping: JointMapping, parts: BodyParts | None = None,
                            params: CorrespondenceParams | None = None) -> np.ndarray:  # fmt: skip
    """Per-vertex features ``(V, 22 + 3)`` (see module doc), weights in :data:`CANONICAL_JOINTS` order."""
    params = params or CorrespondenceParams()
    parts = parts or body_parts(character, mapping)
    _, rest_pos = character.skeleton.rest_global()
    verts = character.vertices.detach().float()
    v_n = verts.shape[0]
    weights = torch.zeros(v_n, len(CANONICAL_JOINTS))
    offsets = torch.zeros(v_n, 3)
    up, forward = torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.0, 0.0, 1.0])
    for s, name in enumerate(parts.names):
        w = parts.weights[:, s].float()
        weights[:, CANONICAL_JOINTS.index(name)] = w
        p = rest_pos[parts.joints[s]].float()
        child = next((c for c in BONE_CHILD.get(name, ()) if c in mapping.joints), None)
        length = None
        if child is not None and float((rest_pos[mapping.joints[child]] - p).norm()) > 1e-4:
            bone = rest_pos[mapping.joints[child]].float() - p
            length = float(bone.norm())
        else:
            parent = CANONICAL_PARENT[name]
            while parent is not None and parent not in mapping.joints:
                parent = CANONICAL_PARENT[parent]
            bone = p - rest_pos[mapping.joints[parent]].float() if parent is not None else up
        rot = _frame(bone, up if name in UP_SECONDARY else forward)
        local = (verts - p) @ rot  # (V, 3) coordinates along (bone, secondary, third)
        own = parts.vertex_part == s
        if length is None:
            length = float(local[own, 0].abs().max()) if own.any() else 1.0
        # Across the bone, measure from the centre of the segment's cross-section (a hip joint is not in the
        # middle of the thigh), in units of the segment's spread.
        centre = local[own, 1:].mean(0) if own.sum() > 2 else torch.zeros(2)
        across = local[:, 1:] - centre
        spread = across[own].pow(2).mean(0).sqrt() if own.sum() > 2 else torch.ones(2)
        scaled = torch.cat([local[:, :1] / max(length, 1e-3), across / spread.clamp_min(1e-3)], dim=1)
        offsets += w[:, None] * scaled
    feats = torch.cat([params.weight_scale * weights, params.offset_scale * offsets], dim=1)
    return feats.numpy().astype(np.float64)


@dataclass
class VertexCorrespondence:
    """Nearest-feature map from source vertices to target vertices."""

    source_features: np.ndarray
    target_features: np.ndarray
    tree: cKDTree

    def map(self, source_vertices: Tensor) -> Tensor:
        """Target vertex indices of the same shape as ``source_vertices`` (any shape of int64)."""
        flat = source_vertices.reshape(-1).numpy()
        if flat.size == 0:
            return source_vertices.clone()
        _, idx = self.tree.query(self.source_features[flat], k=1)
        return torch.from_numpy(np.asarray(idx, dtype=np.int64)).reshape(source_vertices.shape)


def build_correspondence(
    source: Character, source_mapping: JointMapping, target: Character, target_mapping: JointMapping,
    params: CorrespondenceParams | None = None,
) -> VertexCorrespondence:  # fmt: skip
    """The correspondence from ``source``'s vertices to ``target``'s (features of both, a KD-tree on the target)."""
    fs = correspondence_features(source, source_mapping, params=params)
    ft = correspondence_features(target, target_mapping, params=params)
    return VertexCorrespondence(fs, ft, cKDTree(ft))


@dataclass
class ContactConstraints:
    """Vertex pairs that should touch on the target: at ``frame (M,)`` vertices ``i (M,)`` and ``j (M,)``;
    ``hand``/``other`` ``(M,)`` name the source contact's parts (indices into ``part_names``); ``part (M,)``
    the touched body part (index into ``part_clusters``, the body_parts clusters) and ``source_distance (M,)``
    the hand's distance to it on the source (m, 0 inside), or None when not known."""

    num_frames: int
    frame: Tensor
    i: Tensor
    j: Tensor
    hand: Tensor
    other: Tensor
    part_names: list[str]
    part: Tensor | None = None
    source_distance: Tensor | None = None
    part_clusters: tuple[str, ...] = CLUSTERS

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])

    def select_frames(self, start: int, stop: int) -> ContactConstraints:
        """The constraints of frames ``start:stop``, renumbered from 0."""
        keep = (self.frame >= start) & (self.frame < stop)
        return ContactConstraints(
            stop - start, self.frame[keep] - start, self.i[keep], self.j[keep], self.hand[keep], self.other[keep],
            self.part_names, None if self.part is None else self.part[keep],
            None if self.source_distance is None else self.source_distance[keep], self.part_clusters,
        )  # fmt: skip


def transfer_contacts(contacts: SelfContacts, correspondence: VertexCorrespondence) -> ContactConstraints:
    """Source contacts as target vertex-pair constraints (paper 1: pair (i, j) in contact on the source gives
    the constraint that their corresponding target vertices touch)."""
    frame, si, sj = contacts.vertex_pairs()
    p = contacts.pairs.shape[1] if contacts.count else 0
    return ContactConstraints(
        contacts.num_frames,
        frame,
        correspondence.map(si),
        correspondence.map(sj),
        contacts.hand.repeat_interleave(p),
        contacts.other.repeat_interleave(p),
        contacts.part_names,
        contacts.part.repeat_interleave(p) if len(contacts.part) == contacts.count else None,
        contacts.source_distance.repeat_interleave(p) if len(contacts.source_distance) == contacts.count else None,
        tuple(contacts.part_clusters),
    )


def no_contacts(frames: int) -> ContactConstraints:
    """An empty set of constraints for a clip of ``frames`` frames."""
    e = torch.zeros(0, dtype=torch.long)
    return ContactConstraints(frames, e, e, e, e, e, [])


__all__ = [
    "ContactConstraints",
    "CorrespondenceParams",
    "VertexCorrespondence",
    "build_correspondence",
    "correspondence_features",
    "no_contacts",
    "transfer_contacts",
]
