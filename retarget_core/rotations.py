"""Quaternion helpers on torch tensors, quaternions in ``xyzw`` order (glTF and roma), any batch shape.

Thin, named wrappers over roma so that the rest of the code reads as math.
"""

from __future__ import annotations

import roma
import torch
from torch import Tensor


def identity(*shape: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """Identity quaternions of shape ``(*shape, 4)``."""
    q = torch.zeros(*shape, 4, dtype=dtype)
    q[..., 3] = 1.0
    return q


def normalize(q: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` with a non-negative w (canonical sign)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(q[..., 3:4] < 0, -q, q)


def mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` (apply b first, then a), shapes broadcast ``(..., 4)``."""
    a, b = torch.broadcast_tensors(a, b)
    return roma.quat_product(a, b)


def inv(q: Tensor) -> Tensor:
    """Inverse of unit quaternions ``(..., 4)``."""
    return roma.quat_conjugation(q)


def axis_angle(axis: Tensor, angle: Tensor) -> Tensor:
    """Quaternions ``(..., 4)`` from unit axes ``(..., 3)`` and angles ``(...)``."""
    half = 0.5 * angle
    return torch.cat([axis * torch.sin(half)[..., None], torch.cos(half)[..., None]], dim=-1)


def apply(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``, shapes broadcast."""
    batch = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    return roma.quat_action(q.expand(*batch, 4), v.expand(*batch, 3), is_normalized=True)


def to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` from unit quaternions ``(..., 4)``."""
    return roma.unitquat_to_rotmat(q)


def from_matrix(m: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` from rotation matrices ``(..., 3, 3)``; non-orthonormal input is projected."""
    return normalize(roma.rotmat_to_unitquat(roma.special_procrustes(m)))


def from_euler(convention: str, angles: Tensor, degrees: bool = True) -> Tensor:
    """Quaternions ``(..., 4)`` from Euler angles ``(..., D)``; roma's convention string (upper case intrinsic)."""
    return roma.euler_to_unitquat(convention, angles, degrees=degrees)


def to_euler(convention: str, q: Tensor, degrees: bool = True) -> Tensor:
    """Euler angles ``(..., D)`` from unit quaternions ``(..., 4)``."""
    angles = roma.unitquat_to_euler(convention, q, degrees=degrees)
    return angles if isinstance(angles, Tensor) else torch.stack(list(angles), dim=-1)


def between(u: Tensor, v: Tensor) -> Tensor:
    """Shortest-arc rotations ``(..., 4)`` taking directions ``u`` onto ``v`` (both ``(..., 3)``, any length).

    Opposite vectors rotate by 180 degrees about an axis perpendicular to ``u``.
    """
    u, v = torch.broadcast_tensors(u, v)
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w = 1.0 + (u * v).sum(-1, keepdim=True)
    axis = torch.cross(u, v, dim=-1)
    # Fallback axis for opposite vectors: perpendicular to u.
    helper = torch.where(
        u[..., :1].abs() < 0.9,
        torch.tensor([1.0, 0.0, 0.0], dtype=u.dtype),
        torch.tensor([0.0, 1.0, 0.0], dtype=u.dtype),
    )
    perp = torch.cross(u, helper, dim=-1)
    opposite = w < 1e-6
    q = torch.where(opposite, torch.cat([perp, torch.zeros_like(w)], -1), torch.cat([axis, w], -1))
    return normalize(q)


def from_frame(primary: Tensor, secondary: Tensor, primary_axis: int = 1, secondary_axis: int = 2) -> Tensor:
    """Rotation ``(..., 4)`` whose local ``primary_axis`` points along ``primary`` and whose local
    ``secondary_axis`` points as close as possible to ``secondary`` (Gram-Schmidt). Axes: 0=x, 1=y, 2=z."""
    a = primary / primary.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = secondary - (secondary * a).sum(-1, keepdim=True) * a
    b = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    third_axis = 3 - primary_axis - secondary_axis
    c = torch.cross(a, b, dim=-1)
    # Right-handedness: (x, y, z) with x cross y = z.
    if (primary_axis + 1) % 3 != secondary_axis:
        c = -c
    cols = [a, b, c]
    order = [0, 0, 0]
    order[primary_axis], order[secondary_axis], order[third_axis] = 0, 1, 2
    m = torch.stack([cols[order[0]], cols[order[1]], cols[order[2]]], dim=-1)
    return from_matrix(m)


def slerp(a: Tensor, b: Tensor, t: Tensor) -> Tensor:
    """Element-wise spherical interpolation of unit quaternions ``a``, ``b`` ``(..., 4)`` at weights ``t (...)``
    along the shorter arc."""
    dot = (a * b).sum(-1, keepdim=True)
    b = torch.where(dot < 0, -b, b)
    dot = dot.abs().clamp(max=1.0)
    t = t.unsqueeze(-1)
    theta = torch.acos(dot)
    sin = torch.sin(theta)
    small = sin < 1e-6
    wa = torch.where(small, 1 - t, torch.sin((1 - t) * theta) / sin.clamp_min(1e-6))
    wb = torch.where(small, t, torch.sin(t * theta) / sin.clamp_min(1e-6))
    return normalize(wa * a + wb * b)
