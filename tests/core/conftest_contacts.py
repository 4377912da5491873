"""Constructed cases with known answers for the contact, energy and metrics tests (imported by those tests).

- :func:`two_boxes`: a "character" of two boxes, a big one skinned to ``Hips`` and a small one skinned to
  ``LeftHand`` (with a vertex-less ``Spine`` between them so the two are not adjacent segments);
  :func:`box_pose` pushes the small box into the big one's top face by a known depth.
- :func:`hand_on_hip_pose`: the left hand of a real body placed on its hip by optimising the arm's rotations.
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


def hand_on_hip_pose(character: Character, mapping: JointMapping, parts: BodyParts, side: str = "Left",
                     gap: float = -0.004, steps: int = 120) -> tuple[Tensor, Tensor, int]:  # fmt: skip
    """Local rotations ``(J, 4)`` (rest pose, with the arm moved) that put the ``side`` hand's palm on the hip,
    the world translations being the rest ones; returns (local rotations, local translations, hip vertex).

    The arm's rotations (Arm, ForeArm, Hand) are optimised so the hand vertex nearest to a vertex on the outer
    side of the hip lies ``gap`` outside it along the hip's normal (negative: slightly inside, as a hand pressed
    on a body)."""
    sk = character.skeleton
    verts = character.vertices
    hips_part = parts.index("Hips") if side == "Left" else parts.index("Hips")
    sign = 1.0 if side == "Left" else -1.0
    hip_vertices = parts.part_vertices(hips_part)
    hv = verts[hip_vertices]
    # Outer side of the pelvis: far along +x (left) at mid height of the part, facing sideways.
    score = sign * hv[:, 0] - 2.0 * (hv[:, 1] - hv[:, 1].median()).abs()
    hip_vertex = int(hip_vertices[int(score.argmax())])
    normal = character.vertex_normals()[hip_vertex]
    target = verts[hip_vertex] + gap * normal
    chain = [mapping.joints[f"{side}{n}"] for n in ("Arm", "ForeArm", "Hand")]
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
    return r.detach(), sk.rest_translations.clone(), hip_vertex


def _axis_angle(v: Tensor) -> Tensor:
    import roma

    return roma.rotvec_to_unitquat(v)
