"""The energy of paper 1 evaluated on the network's output, for training and for ESO.

A :class:`BodyKit` holds what one target body needs (parts, SDF, rig, dense skin weights); the functions pose
it cheaply: forward kinematics of every frame, skinning of every vertex only on the frames whose
interpenetration is measured, and of the constrained vertices only for the contact term.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.body_parts import BodyParts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.foot_contact import FOOT_JOINTS, FootContacts
from retarget_core.energy.sdf import REFERENCE_HEIGHT_M, PartSDF, segment_matrices
from retarget_core.energy.terms import end_effector_energy, foot_energy, interpenetration_energy, rotation_energy
from retarget_core.model.features import TargetRig, target_rig

END_EFFECTORS = ("LeftHand", "RightHand", "LeftFoot", "RightFoot")


@dataclass
class BodyKit:
    """One target body ready for the energy. weights: ``(V, J)`` dense skin weights; rest_rot/rest_pos:
    ``(J, 4)``/``(J, 3)`` rest world transforms; end_effectors: joint indices of hands and feet;
    foot_joints: the joints of the four foot-contact columns (-1 missing)."""

    character: Character
    mapping: JointMapping
    parts: BodyParts
    sdf: PartSDF
    rig: TargetRig
    weights: Tensor
    rest_rot: Tensor
    rest_pos: Tensor
    end_effectors: list[int]
    foot_joints: list[int]

    @property
    def height(self) -> float:
        return self.rig.height


def body_kit(character: Character, mapping: JointMapping, parts: BodyParts, sdf: PartSDF) -> BodyKit:
    """The :class:`BodyKit` of a body and its cached parts and SDF."""
    rig = target_rig(character.skeleton, mapping, character.vertices, parts)
    rest_rot, rest_pos = character.skeleton.rest_global()
    ee = [mapping.joints[n] for n in END_EFFECTORS if n in mapping.joints]
    feet = [mapping.joints.get(c, -1) for _, c in FOOT_JOINTS]
    return BodyKit(character, mapping, parts, sdf, rig, character.dense_weights().float(), rest_rot, rest_pos, ee, feet)


def skin(kit: BodyKit, grot: Tensor, gpos: Tensor) -> Tensor:
    """Every posed vertex ``(N, V, 3)`` for world joint transforms ``(N, J, 4)``, ``(N, J, 3)``."""
    mats = kinematics.skinning_matrices(kit.rest_rot, kit.rest_pos, grot, gpos)
    return kinematics.linear_blend_skinning(kit.character.vertices.float(), kit.weights, mats)


def vertex_positions(kit: BodyKit, grot: Tensor, gpos: Tensor, frame: Tensor, vertex: Tensor) -> Tensor:
    """Posed positions ``(M, 3)`` of vertices ``vertex (M,)`` at frames ``frame (M,)`` of world joint
    transforms ``(F, J, 4)``, ``(F, J, 3)`` (skins only those vertices)."""
    mats = kinematics.skinning_matrices(kit.rest_rot, kit.rest_pos, grot.index_select(0, frame), gpos.index_select(0, frame))
    blended = torch.einsum("mj,mjk->mk", kit.weights.index_select(0, vertex), mats.flatten(-2)).view(-1, 3, 4)
    v = kit.character.vertices.float().index_select(0, vertex)
    return (blended[..., :3] @ v[:, :, None]).squeeze(-1) + blended[..., 3]


def interpenetration(kit: BodyKit, grot: Tensor, gpos: Tensor) -> Tensor:
    """E_int ``(N,)`` of the frames given (all vertices skinned)."""
    posed = skin(kit, grot, gpos)
    mats = segment_matrices(kit.character, kit.parts, grot, gpos)
    return interpenetration_energy(kit.sdf, posed, mats)


def contact_distance2(kit: BodyKit, grot: Tensor, gpos: Tensor, frame: Tensor, i: Tensor, j: Tensor) -> Tensor:
    """Squared distance ``(M,)`` of each constrained pair at 1.80 m scale (m^2)."""
    s = REFERENCE_HEIGHT_M / kit.height
    d = vertex_positions(kit, grot, gpos, frame, i) - vertex_positions(kit, grot, gpos, frame, j)
    return (d * s).pow(2).sum(-1)


def skeleton_terms(
    kit: BodyKit, rot_out: Tensor, rot_ref: Tensor, gpos_out: Tensor, gpos_ref: Tensor
) -> dict[str, Tensor]:
    """Per frame ``(N,)``: rotation identity term (canonical joints' local rotations vs the reference), root
    velocity term (1.80 m scale) and end-effector velocity term against the reference motion. ``rot (N, J, 4)``,
    ``gpos (N, J, 3)`` where consecutive rows are consecutive frames of one sequence (pass ``(B, F, ...)``
    flattened per sequence through :func:`sequence_terms`)."""
    idx = kit.rig.joints[kit.rig.joints >= 0]
    rotation = rotation_energy(rot_out[..., idx, :], rot_ref[..., idx, :])
    hips = kit.mapping.joints["Hips"]
    s = REFERENCE_HEIGHT_M / kit.height
    vo = gpos_out[1:, hips] - gpos_out[:-1, hips]
    vr = gpos_ref[1:, hips] - gpos_ref[:-1, hips]
    root = torch.cat([torch.zeros_like(vo[:1, 0]), ((vo - vr) * s).pow(2).sum(-1)])
    ee = end_effector_energy(gpos_out[:, kit.end_effectors], gpos_ref[:, kit.end_effectors], kit.height, kit.height)
    return {"rotation": rotation, "root": root, "end_effector": ee}


def feet(kit: BodyKit, gpos: Tensor, labels: Tensor) -> Tensor:
    """E_foot ``(F,)`` of one sequence's world joint positions ``(F, J, 3)`` and planted labels ``(F, 4)``."""
    return foot_energy(gpos, kit.rest_pos, FootContacts(labels, kit.foot_joints), kit.height)


__all__ = [
    "END_EFFECTORS",
    "BodyKit",
    "body_kit",
    "contact_distance2",
    "feet",
    "interpenetration",
    "skeleton_terms",
    "skin",
    "vertex_positions",
]
