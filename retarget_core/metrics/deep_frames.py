"""Why a frame is deeper than 1 cm (issue 22, item 3): which deep frames a joint rotation could still mend and
which no rotation mends with the hands and feet where they are, so a reviewer knows which is which.

Each frame whose deepest penetrating body vertex (the metrics' own depths, beyond the bind pose, at 1.80 m) is
deeper than :data:`DEEP_M` gets one cause, read from that vertex:

- ``fold``: a skinning fold: more than :data:`FOLD_WEIGHT` of its skin weight lies on segments of another part,
  so it is dragged by both sides of a joint and no rotation of either side takes it out of the other.
- ``placement``: the hands and feet hold it there: a vertex of a hand or foot (kept where the source puts it, it
  does not move), or a limb vertex whose frame no turn of the elbow or knee about the line from the limb's root
  joint (shoulder, hip) to its end (wrist, ankle) brings under 1 cm. The vertex, the :data:`SAMPLES` limb vertices
  nearest it at rest and :data:`SAMPLES` spread over the limb (not its hand or foot, which stays) are turned about
  that line every :data:`STEP_DEG` up to :data:`LARGEST_TURN_DEG` either way (a larger turn is another pose) and
  their depths in the parts outside the limb read at each (the limb's own parts turn with them); the frame is at
  least as deep as the deepest of them. Within half a step of an angle read a point moves at most
  ``2 r sin(STEP_DEG / 4)`` (r its distance from the line) and a depth changes no faster than the point moves, so
  the least over the angles of the deepest, less that, is a floor over every turn. Only moving the hand or foot
  (end-effector error) or the limb's root (a shrug) can mend such a frame.
- ``pose``: the others: a joint rotation may mend it (the floor reads a sample of the limb: a denser reading can
  find a ``pose`` frame held; ``placement`` is a sure claim).

The turned vertex is taken as moving rigidly with its limb (a vertex skinned partly to the torso moves less: a fold
when more than :data:`FOLD_WEIGHT` of it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.body_parts import CLUSTERS, BodyParts
from retarget_core.character import Character
from retarget_core.energy.sdf import PartSDF, segment_distance, segment_matrices
from retarget_core.metrics.depth import VertexDepths

DEEP_M = 0.01  # at 1.80 m: ACCEPTANCE.md's "frames > 1 cm"
FOLD_WEIGHT = 0.2  # more skin weight than this on another part's segments: a fold (docs/collisions.md, deep frames)
CAUSES: tuple[str, ...] = ("pose", "placement", "fold")
LIMB_LINES: dict[str, tuple[str, str]] = {  # limb -> the joints its elbow or knee turns about
    "left_arm": ("LeftArm", "LeftHand"), "right_arm": ("RightArm", "RightHand"),
    "left_leg": ("LeftUpLeg", "LeftFoot"), "right_leg": ("RightUpLeg", "RightFoot"),
}  # fmt: skip
LARGEST_TURN_DEG = 70.0  # a larger turn of the elbow or knee is another pose (the swivel stage's largest)
STEP_DEG = 5.0  # the turns read, this far apart
SAMPLES = 64  # vertices of the limb near the deepest, and as many spread over it, read with it at each turn
CHUNK = 256  # deep frames read together (their turned samples: about 25 MB)
HELD_SEGMENTS = frozenset({"LeftHand", "RightHand", "LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase"})


@dataclass(frozen=True)
class DeepFrames:
    """deep: ``(F,)`` frames deeper than 1 cm; cause: ``(F,)`` index into :data:`CAUSES` of each of them, -1
    elsewhere (None: not read)."""

    deep: Tensor
    cause: Tensor | None = None

    def percent(self) -> float | None:
        """The share (%) of frames deeper than 1 cm (None without frames)."""
        return round(100.0 * float(self.deep.float().mean()), 4) if len(self.deep) else None

    def percent_by_cause(self) -> dict[str, float] | None:
        """That share split by cause (the entries add up to :meth:`percent`; None when not read)."""
        if self.cause is None or not len(self.cause):
            return None
        return {c: round(100.0 * float((self.cause == i).float().mean()), 4) for i, c in enumerate(CAUSES)}


def deep_frames(character: Character, sdf: PartSDF, depths: VertexDepths, grot: Tensor, gpos: Tensor,
                joint_of: dict[str, int], scale_to_180: float, causes: bool = True) -> DeepFrames:  # fmt: skip
    """The frames deeper than 1 cm from the per-vertex ``depths`` (m, the body's scale; ``sdf``'s measure) and,
    with ``causes``, why, from the world joint transforms ``grot (F, J, 4)``, ``gpos (F, J, 3)`` and ``joint_of``
    (canonical name -> joint)."""
    deep_m = DEEP_M / scale_to_180
    frame, vertex, _, _ = depths.deepest(deep_m, 1)
    deep = torch.zeros(depths.num_frames, dtype=torch.bool)
    deep[frame] = True
    if not causes:
        return DeepFrames(deep)
    cause = torch.full((depths.num_frames,), -1, dtype=torch.long)
    for s in range(0, len(frame), CHUNK):  # chunks of deep frames: a long clip's turned samples stay small
        f, v = frame[s : s + CHUNK], vertex[s : s + CHUNK]
        held = _held(character, sdf, v, deep_m, grot[f], gpos[f], joint_of)
        fold = foreign_weight(sdf.parts, v) > FOLD_WEIGHT
        cause[f] = torch.where(fold, CAUSES.index("fold"), torch.where(held, CAUSES.index("placement"), 0))
    return DeepFrames(deep, cause)


def foreign_weight(parts: BodyParts, vertex: Tensor) -> Tensor:
    """``(K,)`` the share of each vertex's segment weight on segments of another part than its dominant one's."""
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    weights = parts.weights[vertex].clamp_min(0.0)  # (K, S)
    own = cluster[None, :] == cluster[parts.vertex_part[vertex]][:, None]
    return 1.0 - (weights * own).sum(1) / weights.sum(1).clamp_min(1e-12)


def _held(character: Character, sdf: PartSDF, vertex: Tensor, deep_m: float, grot: Tensor, gpos: Tensor,
          joint_of: dict[str, int]) -> Tensor:  # fmt: skip
    """``(K,)`` True where vertex ``k``, the deepest at the frame whose world transforms are ``grot[k]``,
    ``gpos[k]``, is a hand or foot vertex, or its frame stays deeper than ``deep_m`` however the limb turns."""
    parts = sdf.parts
    seg = parts.vertex_part[vertex]
    held_segment = torch.tensor([n in HELD_SEGMENTS for n in parts.names], dtype=torch.bool)  # (S,)
    out = held_segment[seg]
    segment_cluster = torch.tensor(parts.cluster, dtype=torch.long)  # (S,)
    mats = segment_matrices(character, parts, grot, gpos).double()  # (K, S, 3, 4)
    for limb, (root, end) in LIMB_LINES.items():
        mine = (segment_cluster[seg] == CLUSTERS.index(limb)) & ~out
        if root not in joint_of or end not in joint_of or not bool(mine.any()):
            continue
        turning = ~held_segment & (segment_cluster == CLUSTERS.index(limb))  # (S,) the limb's segments that turn
        rows = _limb_samples(character, parts, vertex[mine], turning)  # (k, M)
        at = _posed_at(character, rows, grot[mine], gpos[mine])
        a, b = gpos[mine, joint_of[root]].double(), gpos[mine, joint_of[end]].double()
        least = _least_turned_depth(sdf, rows, at, a, b, mats[mine], CLUSTERS.index(limb))
        out[mine] = least > deep_m
    return out


def _limb_samples(character: Character, parts: BodyParts, vertex: Tensor, turning: Tensor) -> Tensor:
    """``(K, 1 + 2 SAMPLES)`` each vertex, then :data:`SAMPLES` body vertices of the segments ``turning (S,)``
    (bool: its limb's that turn with it, not the hand's or foot's) nearest it at rest and :data:`SAMPLES` evenly
    through the others."""
    body = parts.body if parts.body is not None else torch.ones(len(parts.vertex_part), dtype=torch.bool)
    limb_vertices = torch.nonzero(turning[parts.vertex_part] & body).flatten()
    spread = limb_vertices[torch.linspace(0, len(limb_vertices) - 1, SAMPLES).round().long()]
    rest = character.vertices[limb_vertices]
    near_n = min(SAMPLES, len(limb_vertices))
    rows = []
    for v in vertex.tolist():
        near = limb_vertices[(rest - character.vertices[v]).norm(dim=-1).topk(near_n, largest=False).indices]
        rows.append(torch.cat([torch.tensor([v]), near, near[:1].expand(SAMPLES - near_n), spread]))
    return torch.stack(rows)


def _posed_at(character: Character, vertex: Tensor, grot: Tensor, gpos: Tensor) -> Tensor:
    """``(K, M, 3)`` float64: vertices ``vertex[k] (M,)`` posed by the world transforms ``grot[k] (J, 4)``,
    ``gpos[k]``."""
    rest_rot, rest_pos = character.skeleton.rest_global()
    mats = kinematics.skinning_matrices(rest_rot, rest_pos, grot, gpos).double()  # (K, J, 3, 4)
    joints, weights = character.skin_joints[vertex].long(), character.skin_weights[vertex].double()  # (K, M, I)
    picked = mats[torch.arange(len(vertex))[:, None, None], joints]  # (K, M, I, 3, 4)
    blended = (picked * weights[..., None, None]).sum(2)  # (K, M, 3, 4)
    rest = character.vertices[vertex].double()
    return (blended[..., :3] @ rest[..., None]).squeeze(-1) + blended[..., 3]


def _least_turned_depth(sdf: PartSDF, vertex: Tensor, at: Tensor, a: Tensor, b: Tensor, mats: Tensor,
                        limb: int) -> Tensor:  # fmt: skip
    """``(K,)`` a floor, over every turn about the line through ``a[k]`` and ``b[k]`` (3,), of the deepest of
    vertices ``vertex[k] (M,)`` (of cluster ``limb``, posed at ``at[k] (M, 3)``) in the segments outside it each is
    tested against; ``mats (K, S, 3, 4)`` the segments' skinning transforms."""
    k_n, m_n = vertex.shape
    axis = (b - a) / (b - a).norm(dim=-1, keepdim=True).clamp_min(1e-12)
    angles = torch.deg2rad(
        torch.arange(-LARGEST_TURN_DEG, LARGEST_TURN_DEG + 0.5 * STEP_DEG, STEP_DEG, dtype=torch.float64)
    )
    t_n = len(angles)
    rel = (at - a[:, None]).reshape(-1, 3)
    points = a[:, None, None] + _turned(rel, axis.repeat_interleave(m_n, 0), angles).view(k_n, m_n, t_n, 3)
    depth = torch.zeros(k_n, m_n, t_n, dtype=torch.float64)
    own = sdf.parts.vertex_part[vertex]  # (K, M)
    for j in range(sdf.parts.num_parts):
        tested = sdf.allowed[own, j].bool()  # (K, M)
        if sdf.grids[j] is None or sdf.parts.cluster[j] == limb or not bool(tested.any()):
            continue
        f = torch.nonzero(tested.any(dim=1)).flatten()
        r, t = mats[f, j, :, :3], mats[f, j, :, 3]
        local = ((points[f] - t[:, None, None]) @ r[:, None]).reshape(-1, 3)  # R^T (p - t), row-wise
        lo = sdf.origin[j].double()
        hi = lo + (sdf.size[j] - 1).double() * float(sdf.voxel[j])
        near = ((local >= lo) & (local <= hi)).all(dim=-1)  # outside its grid a point is outside the segment
        if not bool(near.any()):
            continue
        d = torch.zeros(len(local), dtype=torch.float64)  # (the grid reaches a margin wider than the blend)
        d[near] = -segment_distance(sdf, j, local[near]).double()
        d = d.view(len(f), m_n, t_n)
        rows = vertex[f]
        d = (d - sdf.rest_depth[rows, j].double()[..., None]).clamp_min(0.0) * sdf.geodesic_weight[rows, j].double()[
            ..., None
        ]
        depth[f] = torch.maximum(depth[f], d * tested[f, :, None])
    slack = (
        2.0
        * _line_distance(rel, axis.repeat_interleave(m_n, 0)).view(k_n, m_n, 1)
        * math.sin(math.radians(STEP_DEG) / 4.0)
    )
    return (depth - slack).amax(dim=1).amin(dim=1)


def _turned(v: Tensor, axis: Tensor, angles: Tensor) -> Tensor:
    """``(K, T, 3)`` vectors ``v (K, 3)`` turned about the unit ``axis (K, 3)`` by each of ``angles (T,)``."""
    turn = rot.axis_angle(axis[:, None, :], angles[None, :].expand(len(axis), -1))  # (K, T, 4)
    return rot.apply(turn, v[:, None, :])


def _line_distance(rel: Tensor, axis: Tensor) -> Tensor:
    """``(K,)`` distance of points ``rel (K, 3)``, given from a point of the line, from the line along the unit
    ``axis (K, 3)``."""
    return (rel - (rel * axis).sum(-1, keepdim=True) * axis).norm(dim=-1)


__all__ = ["CAUSES", "DEEP_M", "FOLD_WEIGHT", "DeepFrames", "deep_frames", "foreign_weight"]
