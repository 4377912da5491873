"""Contact-rich training motion: analytic two-bone IK that brings a hand onto the body (hips, belly, thigh,
face, the other hand) over a window of a clip, blended in and out, on the source's own 22-joint body.

The hand's palm centre (the centroid of its dominant vertices, fixed in the hand's frame) is driven to a point
just outside a body vertex that moves with the body; the hand keeps its world rotation; the elbow stays in the
plane of the original arm (its pole).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.body_parts import BodyParts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.kinematics import forward_kinematics, global_to_local
from retarget_core.motion import Motion

# Target regions: (segment names, required normal direction in the rest pose (None: any), share of draws).
# "side" is the hand's own side (+X for the left hand).
REGIONS: dict[str, tuple[tuple[str, ...], str | None]] = {
    "hips": (("Hips", "Spine"), "side"),
    "belly": (("Spine", "Spine1"), "front"),
    "thigh": (("UpLeg",), "front"),
    "face": (("Head",), "front"),
    "other_hand": (("Hand",), None),
    "chest": (("Spine2",), "front"),
}
RAMP_FRAMES = 8  # blend in and out over about 0.27 s at 30 fps
CONTACT_OFFSET_M = 0.010  # palm centre this far outside the surface (at 1.80 m): about half a hand's thickness
NORMAL_MIN_DOT = 0.6  # a "front" or "side" vertex's rest normal is within about 53 degrees of that direction
REACH_LIMIT = 0.995  # share of the arm's full length the IK may stretch to


@dataclass
class ContactWindow:
    """An augmented window: the modified motion (on the source body) and what was asked of it."""

    motion: Motion
    hand: str
    region: str


def _smooth_weight(n: int, ramp: int) -> Tensor:
    t = torch.ones(n)
    r = min(ramp, n // 2)
    if r > 0:
        x = torch.arange(r, dtype=torch.float32) / r
        s = x * x * (3 - 2 * x)
        t[:r], t[n - r :] = s, s.flip(0)
    return t


def two_bone_ik(a: Tensor, b: Tensor, c: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """New elbow ``(F, 3)`` and wrist ``(F, 3)`` of the chain shoulder ``a``, elbow ``b``, wrist ``c`` ``(F, 3)``
    reaching ``target (F, 3)``, the elbow in the plane of the original arm."""
    l1, l2 = (b - a).norm(dim=-1, keepdim=True), (c - b).norm(dim=-1, keepdim=True)
    to = target - a
    dist = to.norm(dim=-1, keepdim=True).clamp(min=(l1 - l2).abs() + 1e-4, max=REACH_LIMIT * (l1 + l2))
    d = to / to.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    pole = (b - a) - ((b - a) * d).sum(-1, keepdim=True) * d
    fallback = torch.tensor([0.0, 0.0, -1.0]).expand_as(pole)
    pole = torch.where(pole.norm(dim=-1, keepdim=True) < 1e-5, fallback, pole)
    u = pole / pole.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    cos_a = ((l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist)).clamp(-1.0, 1.0)
    elbow = a + l1 * (cos_a * d + torch.sqrt(1 - cos_a * cos_a) * u)
    return elbow, a + dist * d


def _candidate_vertices(body: Character, parts: BodyParts, region: str, side: str) -> Tensor:
    names, direction = REGIONS[region]
    other = "Right" if side == "Left" else "Left"
    segs = []
    for name in names:
        full = name if name in ("Hips", "Spine", "Spine1", "Spine2", "Head") else (other if region == "other_hand" else side) + name
        if full in parts.names:
            segs.append(parts.index(full))
    mask = torch.zeros(body.num_vertices, dtype=torch.bool)
    for s in segs:
        mask |= parts.vertex_part == s
    if direction is not None:
        normals = body.vertex_normals()
        axis = torch.tensor([0.0, 0.0, 1.0]) if direction == "front" else torch.tensor([1.0 if side == "Left" else -1.0, 0.0, 0.0])
        mask &= (normals @ axis) > NORMAL_MIN_DOT
    return torch.nonzero(mask).flatten()


def contact_window(
    body: Character, mapping: JointMapping, parts: BodyParts, motion: Motion, rng: np.random.Generator,
    start: int, length: int,
) -> ContactWindow | None:  # fmt: skip
    """Frames ``start:start+length`` of ``motion`` (on ``body``'s 22-joint skeleton) with one hand brought onto
    a random region (None when no candidate vertex exists)."""
    window = motion.slice(start, start + length)
    side = "Left" if rng.random() < 0.5 else "Right"
    region = list(REGIONS)[int(rng.integers(len(REGIONS)))]
    cand = _candidate_vertices(body, parts, region, side)
    if len(cand) == 0:
        return None
    vertex = int(cand[int(rng.integers(len(cand)))])
    m = mapping.joints
    arm, fore, hand = m[f"{side}Arm"], m[f"{side}ForeArm"], m[f"{side}Hand"]
    grot, gpos = window.global_transforms()
    rest_rot, rest_pos = body.skeleton.rest_global()
    with torch.no_grad():
        posed = body.pose_vertices(grot, gpos)
    normals = body.vertex_normals()
    # Vertex normal carried by its dominant segment's rotation.
    seg_joint = parts.joints[int(parts.vertex_part[vertex])]
    seg_delta = rot.mul(grot[:, seg_joint], rot.inv(rest_rot[seg_joint]))
    n_t = rot.apply(seg_delta, normals[vertex].expand(length, 3))
    scale = body.height / 1.80
    surface = posed[:, vertex] + CONTACT_OFFSET_M * scale * n_t
    palm_rest = body.vertices[parts.vertex_part == parts.index(f"{side}Hand")].mean(0) - rest_pos[hand]
    hand_delta = rot.mul(grot[:, hand], rot.inv(rest_rot[hand]))
    palm = rot.apply(hand_delta, palm_rest.expand(length, 3))
    wrist_goal = surface - palm
    w = _smooth_weight(length, RAMP_FRAMES)[:, None]
    goal = gpos[:, hand] + w * (wrist_goal - gpos[:, hand])
    elbow, wrist = two_bone_ik(gpos[:, arm], gpos[:, fore], gpos[:, hand], goal)
    r_arm = rot.mul(rot.between(gpos[:, fore] - gpos[:, arm], elbow - gpos[:, arm]), grot[:, arm])
    fore_dir = rot.apply(rot.mul(r_arm, rot.inv(grot[:, arm])), gpos[:, hand] - gpos[:, fore])
    swing = rot.mul(r_arm, rot.inv(grot[:, arm]))
    r_fore = rot.mul(rot.between(fore_dir, wrist - elbow), rot.mul(swing, grot[:, fore]))
    new_grot, new_gpos = grot.clone(), gpos.clone()
    new_grot[:, arm], new_grot[:, fore] = rot.normalize(r_arm), rot.normalize(r_fore)
    new_gpos[:, fore], new_gpos[:, hand] = elbow, wrist
    for j, p in enumerate(body.skeleton.parents):  # joints below the hand follow it rigidly
        if p == hand:
            new_gpos[:, j] = wrist + rot.apply(grot[:, hand], window.translations[:, j])
    local_r, _ = global_to_local(body.skeleton.parents, new_grot, new_gpos)
    out_r = window.rotations.clone()
    for j in (arm, fore, hand):
        out_r[:, j] = local_r[:, j]
    out = Motion(window.skeleton, window.fps, out_r, window.translations.clone(), f"{motion.name}+{side}{region}")
    _, check = forward_kinematics(body.skeleton.parents, out.rotations, out.translations)
    assert torch.allclose(check[:, hand], wrist, atol=1e-3), "IK result does not reproduce the wrist goal"
    return ContactWindow(out, side, region)


__all__ = ["REGIONS", "ContactWindow", "contact_window", "two_bone_ik"]
