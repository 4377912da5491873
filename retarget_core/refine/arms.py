"""A character's arms as the hand stages move them: which joints make each arm, and the elbow swivel (the arm
turned about its shoulder-to-wrist axis, so the hand stays where it is).

The stages that move arms after the collision stage (:mod:`retarget_core.refine.hand_contacts` moves a wrist by
two-bone IK; :mod:`retarget_core.refine.arm_swivel` swings the elbow) share these.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.canonical import JointMapping
from retarget_core.motion import Motion
from retarget_core.skeleton import subtree


@dataclass(frozen=True)
class Arm:
    """One arm's joints (indices into the skeleton) and its hand's index in
    :data:`retarget_core.metrics.acceptance_body.HANDS` (0 left, 1 right); ``followers``: joints mapped as this
    hand's fingers that hang from the forearm chain, not from the hand (a thumb on the forearm, as on the
    Quaternius rigs): they keep their world rotation with the hand."""

    upper: int
    fore: int
    hand: int
    side: int
    followers: tuple[int, ...] = ()


def arms_of(mapping: JointMapping, parents: list[int]) -> list[Arm]:
    """The arms whose three joints ``mapping`` maps (left, right), on a skeleton of ``parents``."""
    out = []
    for side, prefix in enumerate(("Left", "Right")):
        upper, fore, hand = (mapping.joints.get(f"{prefix}{n}") for n in ("Arm", "ForeArm", "Hand"))
        if upper is None or fore is None or hand is None:
            continue
        in_hand = set(subtree(parents, hand))
        fingers = [j for name, j in mapping.extras.items() if name.startswith(f"{prefix}Hand")]
        roots = [j for j in fingers if j not in in_hand and parents[j] not in in_hand and parents[j] not in fingers]
        followers = tuple(roots)  # the first joint of each such finger: the rest follow it
        out.append(Arm(upper, fore, hand, side, followers))
    return out


def about_axis(axis: Tensor, angle: Tensor) -> Tensor:
    """Quaternions ``(..., 4)`` turning by ``angle (...)`` radians about unit ``axis (..., 3)``."""
    half = angle[..., None] / 2
    return torch.cat([axis * torch.sin(half), torch.cos(half)], dim=-1)


def swivel_arms(motion: Motion, arms: list[Arm], angles: Tensor) -> Motion:
    """The motion with each arm turned by ``angles (F, 2)`` radians (by hand side) about its shoulder-to-wrist
    axis: the wrist stays, the hand and the followers keep their world rotation, the elbow swings; frames and
    arms at angle 0 keep their rotations bit for bit."""
    sk = motion.skeleton
    grot, gpos = motion.global_transforms()
    local = motion.rotations.clone()
    for arm in arms:
        idx = torch.nonzero(angles[:, arm.side] != 0).flatten()
        if idx.numel() == 0:
            continue
        axis = gpos[idx, arm.hand] - gpos[idx, arm.upper]
        axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        q = about_axis(axis, angles[idx, arm.side].to(axis.dtype)).to(grot.dtype)
        parent = sk.parents[arm.upper]
        local[idx, arm.upper] = rot.normalize(rot.mul(rot.inv(grot[idx, parent]), rot.mul(q, grot[idx, arm.upper])))
        for j in (arm.hand, *arm.followers):  # world rotation kept: undo the turn their parent now carries
            par = rot.mul(q, grot[idx, sk.parents[j]])
            local[idx, j] = rot.normalize(rot.mul(rot.inv(par), grot[idx, j]))
    return Motion(sk, motion.fps, local, motion.translations.clone(), motion.name)


__all__ = ["Arm", "about_axis", "arms_of", "swivel_arms"]
