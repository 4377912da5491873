"""Constructed cases with known answers for the contact, energy and metrics tests (imported by those tests).

- :func:`two_boxes`: a "character" of two boxes, a big one skinned to ``Hips`` and a small one skinned to
  ``LeftHand`` (with a vertex-less ``Spine`` between them so the two are not adjacent segments);
  :func:`box_pose` pushes the small box into the big one's top face by a known depth.
- :func:`hand_on_vertex_pose`: a hand of a real body placed on a chosen vertex (hip, cheek, thigh: see
  :func:`hip_vertex`, :func:`cheek_vertex`, :func:`thigh_vertices`) by optimising the arm's rotations;
  :func:`hand_on_hip_pose` on the hip.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from torch import Tensor

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.body_parts import BodyParts, mapping_by_name
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.skeleton import Skeleton

BIG = 0.4  # edge of the box skinned to Hips, standing on y = 0, centred on x = z = 0
SMALL = 0.1  # edge of the box skinned to LeftHand, at rest beside the big one
SMALL_REST_CENTRE = (1.0, 0.5, 0.0)


def _box(extent: float, centre: tuple[float, float, float], subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.box(extents=(extent, extent, extent))
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    for _ in range(subdivisions):
        v, f = trimesh.remesh.subdivide(v, f)
    return v + np.asarray(centre), f


def two_boxes(dtype: torch.dtype = torch.float32) -> tuple[Character, JointMapping]:
    """The two-box character and its mapping (joints Hips, Spine, LeftHand)."""
    vb, fb = _box(BIG, (0.0, BIG / 2, 0.0))
    va, fa = _box(SMALL, SMALL_REST_CENTRE)
    verts = np.concatenate([vb, va])
    faces = np.concatenate([fb, fa + len(vb)])
    joints = torch.zeros(len(verts), 1, dtype=torch.long)
    joints[len(vb) :] = 2
    weights = torch.ones(len(verts), 1, dtype=dtype)
    hips = torch.tensor([0.0, BIG / 2, 0.0])
    spine = torch.tensor([0.0, 0.1, 0.0])
    hand = torch.tensor(SMALL_REST_CENTRE) - hips - spine
    sk = Skeleton(["Hips", "Spine", "LeftHand"], [-1, 0, 1], torch.stack([hips, spine, hand]).to(dtype), rot.identity(3, dtype=dtype))
    ch = Character("two_boxes", sk, torch.tensor(verts, dtype=dtype), torch.tensor(faces, dtype=torch.long), joints, weights)
    return ch, mapping_by_name(sk.names)


def box_pose(depth: float | Tensor, frames: int = 1, dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """World joint rotations ``(F, 3, 4)`` and positions ``(F, 3, 3)`` putting the small box centred above the
    big one with its bottom face ``depth`` below the big box's top face (negative depth: a gap)."""
    depth = torch.as_tensor(depth, dtype=dtype)
    grot = rot.identity(frames, 3, dtype=dtype)
    hips = torch.tensor([0.0, BIG / 2, 0.0], dtype=dtype)
    spine = hips + torch.tensor([0.0, 0.1, 0.0], dtype=dtype)
    hand = torch.stack([torch.zeros((), dtype=dtype), BIG + SMALL / 2 - depth, torch.zeros((), dtype=dtype)])
    gpos = torch.stack([hips, spine, hand]).expand(frames, 3, 3).clone()
    return grot, gpos


def hip_vertex(character: Character, parts: BodyParts, side: str = "Left") -> int:
    """A vertex on the outer side of the pelvis (far along +x for the left side, at mid height of the part)."""
    sign = 1.0 if side == "Left" else -1.0
    hip_vertices = parts.part_vertices(parts.index("Hips"))
    hv = character.vertices[hip_vertices]
    score = sign * hv[:, 0] - 2.0 * (hv[:, 1] - hv[:, 1].median()).abs()
    return int(hip_vertices[int(score.argmax())])


def cheek_vertex(character: Character, parts: BodyParts, side: str = "Left") -> int:
    """A vertex on the ``side`` cheek: the head vertex farthest to that side and forward, between a quarter and
    a half of the head's height."""
    sign = 1.0 if side == "Left" else -1.0
    head = parts.part_vertices(parts.index("Head"))
    hv = character.vertices[head]
    lo, hi = float(hv[:, 1].min()), float(hv[:, 1].max())
    band = (hv[:, 1] > lo + 0.3 * (hi - lo)) & (hv[:, 1] < lo + 0.5 * (hi - lo))
    score = sign * hv[:, 0] + 0.6 * hv[:, 2]
    score[~band] = -torch.inf
    return int(head[int(score.argmax())])


def thigh_vertices(character: Character, parts: BodyParts, side: str = "Left", count: int = 4) -> list[int]:
    """``count`` vertices down the outer side of the ``side`` thigh, from a third to two thirds of its length."""
    sign = 1.0 if side == "Left" else -1.0
    thigh = parts.part_vertices(parts.index(f"{side}UpLeg"))
    tv = character.vertices[thigh]
    lo, hi = float(tv[:, 1].min()), float(tv[:, 1].max())
    out = []
    for k in range(count):
        y = hi - (0.3 + 0.35 * k / max(count - 1, 1)) * (hi - lo)
        score = sign * tv[:, 0] - 4.0 * (tv[:, 1] - y).abs()
        out.append(int(thigh[int(score.argmax())]))
    return out


def hand_on_vertex_pose(character: Character, mapping: JointMapping, parts: BodyParts, vertex: int,
                        side: str = "Left", gap: float = -0.004, steps: int = 120,
                        joints: tuple[str, ...] = ("Arm", "ForeArm", "Hand")) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Local rotations ``(J, 4)`` (rest pose, with the arm moved) that put the ``side`` hand on rest vertex
    ``vertex``, the local translations being the rest ones; returns (local rotations, local translations).

    The arm's rotations (``joints`` of the side) are optimised so the hand vertex nearest to the point ``gap``
    outside ``vertex`` along its normal lies on that point (negative gap: slightly inside, as a hand pressed on
    a body)."""
    sk = character.skeleton
    verts = character.vertices
    normal = character.vertex_normals()[vertex]
    target = verts[vertex] + gap * normal
    chain = [mapping.joints[f"{side}{n}"] for n in joints]
    hand = parts.group(f"{side}Hand")[::3]  # a third of the hand's vertices is plenty to place it
    local_rot = sk.rest_rotations.clone()
    params = torch.zeros(len(chain), 3, requires_grad=True)
    opt = torch.optim.Adam([params], lr=0.05)
    rest_rot, rest_pos = sk.rest_global()
    dense = character.dense_weights()[hand]
    for _ in range(steps):
        r = local_rot.clone()
        for k, j in enumerate(chain):
            r[j] = rot.mul(sk.rest_rotations[j], _axis_angle(params[k]))
        grot, gpos = kinematics.forward_kinematics(sk.parents, r, sk.rest_translations)
        mats = kinematics.skinning_matrices(rest_rot, rest_pos, grot, gpos)
        x = kinematics.linear_blend_skinning(verts[hand], dense, mats)
        d = (x - target).norm(dim=-1)
        loss = d.min() ** 2 + 1e-3 * (x.mean(0) - target).norm() ** 2 + 1e-4 * params.pow(2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        r = local_rot.clone()
        for k, j in enumerate(chain):
            r[j] = rot.mul(sk.rest_rotations[j], _axis_angle(params[k]))
    return r.detach(), sk.rest_translations.clone()


def hand_on_hip_pose(character: Character, mapping: JointMapping, parts: BodyParts, side: str = "Left",
                     gap: float = -0.004, steps: int = 120) -> tuple[Tensor, Tensor, int]:  # fmt: skip
    """The ``side`` hand's palm on the outer side of the hip (:func:`hand_on_vertex_pose`); returns (local
    rotations, local translations, hip vertex)."""
    vertex = hip_vertex(character, parts, side)
    local_r, local_t = hand_on_vertex_pose(character, mapping, parts, vertex, side, gap, steps)
    return local_r, local_t, vertex


def _axis_angle(v: Tensor) -> Tensor:
    import roma

    return roma.rotvec_to_unitquat(v)
