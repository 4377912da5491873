"""Analytic two-bone inverse kinematics (hip-knee-ankle), batched over any leading dimensions.

The method of orangeduck's Motion-Matching ``ik_two_bone`` (see METHOD-NOTES.md), in world space:
1. bend: the law of cosines gives the thigh angle at the hip and the interior angle at the knee that put the
   ankle at the target's distance from the hip; both rotations turn about one axis, ``(c - a) x pole``, so the
   knee bends toward the pole (the knee's own forward axis: it cannot flip backward, and a straight leg still
   has a well-defined bending plane);
2. swing: the shortest arc taking the bent chain's hip-to-ankle direction onto hip-to-target.
The reach is clamped to ``max_reach`` times the full leg length (short of full extension, where the knee's
angle is ill-conditioned and snaps) or to the leg's own extension in the pose given, whichever is longer (a leg
the input holds straighter is not bent to the clamp: that bend, on a few frames, is a jerk at the knee), and
never below a small fraction of it; no NaN for any input.
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core import rotations as rot

EPS = 1e-8
MIN_REACH_FRACTION = 0.01  # a target at the hip itself is clamped to this share of the leg length


def _unit(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(EPS)


def _angle(u: Tensor, v: Tensor) -> Tensor:
    """Unsigned angle ``(...)`` between vectors ``(..., 3)``."""
    return torch.acos((_unit(u) * _unit(v)).sum(-1).clamp(-1.0, 1.0))


def _between(u: Tensor, v: Tensor) -> Tensor:
    """Shortest-arc quaternions ``(..., 4)`` taking directions ``u`` to ``v`` (antiparallel: a half turn about
    an axis perpendicular to ``u``)."""
    u, v = _unit(u), _unit(v)
    w = 1.0 + (u * v).sum(-1, keepdim=True)
    xyz = torch.cross(u, v, dim=-1)
    anti = w[..., 0] < 1e-6
    if bool(anti.any()):
        other = torch.where(u[..., :1].abs() < 0.9, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
        perp = _unit(torch.cross(u, other.expand_as(u), dim=-1))
        xyz = torch.where(anti[..., None], perp, xyz)
        w = torch.where(anti[..., None], torch.zeros_like(w), w)
    return rot.normalize(torch.cat([xyz, w], dim=-1))


def two_bone_ik(
    hip: Tensor,
    knee: Tensor,
    ankle: Tensor,
    target: Tensor,
    pole: Tensor,
    hip_rotation: Tensor,
    knee_rotation: Tensor,
    max_reach: float = 0.995,
    iterations: int = 2,
) -> tuple[Tensor, Tensor]:
    """New world rotations ``(..., 4)`` of the thigh and the shin that put the ankle at ``target``.

    hip, knee, ankle, target: world positions ``(..., 3)``; pole: ``(..., 3)`` the direction the knee should
    point (the knee's forward axis); hip_rotation, knee_rotation: current world rotations ``(..., 4)`` of the
    hip joint (thigh) and the knee joint (shin). Bone lengths are those of the current pose. ``max_reach``:
    the largest hip-to-target distance as a share of the leg's full length, or the leg's own hip-to-ankle share
    where that is longer (targets beyond it are reached as far as that along the same direction).
    ``iterations``: passes of bend-then-swing (the first is exact for a bent knee; the second removes what a
    nearly straight knee's blended hinge axis leaves).
    """
    full = ((knee - hip).norm(dim=-1) + (ankle - knee).norm(dim=-1)).clamp_min(EPS)
    reach_cap = torch.clamp_min((ankle - hip).norm(dim=-1) / full, max_reach)  # (...) the input's own, or more
    for _ in range(iterations):
        hip_rotation, knee_rotation, knee, ankle = _solve(
            hip, knee, ankle, target, pole, hip_rotation, knee_rotation, reach_cap
        )
    return hip_rotation, knee_rotation


# Weight of the pole in the knee's hinge axis: the hinge is the knee's own plane where the leg is bent
# (|sin bend| >> this) and the plane through the pole where it is nearly straight (bends under ~3 degrees).
POLE_WEIGHT = 0.05


def _solve(
    hip: Tensor, knee: Tensor, ankle: Tensor, target: Tensor, pole: Tensor,
    hip_rotation: Tensor, knee_rotation: Tensor, reach_cap: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """One bend-then-swing pass (``reach_cap (...)``: the largest reach as a share of the full length); returns
    the new rotations and the new knee and ankle positions."""
    thigh, shin = knee - hip, ankle - knee
    l_thigh = thigh.norm(dim=-1).clamp_min(EPS)
    l_shin = shin.norm(dim=-1).clamp_min(EPS)
    full = l_thigh + l_shin
    reach_lo = torch.maximum(MIN_REACH_FRACTION * full, (l_thigh - l_shin).abs() * 1.001 + EPS)
    reach = (target - hip).norm(dim=-1)
    reach = torch.minimum(torch.maximum(reach, reach_lo), reach_cap * full)
    # Hinge axis: the knee's plane (oriented so a positive turn straightens it), the pole where it is straight.
    plane = torch.cross(shin, thigh, dim=-1) / (l_thigh * l_shin)[..., None]
    chain = ankle - hip
    toward_pole = torch.cross(chain, _unit(pole), dim=-1) / chain.norm(dim=-1, keepdim=True).clamp_min(EPS)
    hinge = plane + POLE_WEIGHT * toward_pole
    fallback = torch.cross(_unit(chain), torch.tensor([1.0, 0.0, 0.0]).expand_as(chain), dim=-1)
    hinge = _unit(torch.where(hinge.norm(dim=-1, keepdim=True) < 1e-9, fallback, hinge))
    # Interior knee angle now and wanted (law of cosines).
    knee_angle_0 = _angle(-thigh, shin)
    cos_knee = (l_thigh**2 + l_shin**2 - reach**2) / (2.0 * l_thigh * l_shin)
    knee_angle_1 = torch.acos(cos_knee.clamp(-1.0, 1.0))
    r_knee = rot.axis_angle(hinge, knee_angle_1 - knee_angle_0)
    ankle_1 = knee + rot.apply(r_knee, shin)
    # Swing the whole chain about the hip so hip->ankle points at the target.
    swing = _between(ankle_1 - hip, target - hip)
    new_hip = rot.normalize(rot.mul(swing, hip_rotation))
    new_knee = rot.normalize(rot.mul(swing, rot.mul(r_knee, knee_rotation)))
    knee_2 = hip + rot.apply(swing, thigh)
    ankle_2 = hip + rot.apply(swing, ankle_1 - hip)
    return new_hip, new_knee, knee_2, ankle_2


__all__ = ["two_bone_ik"]
