"""The energy terms of paper 1 (section 3.1) in torch: one value per frame ``(F,)``, differentiable.

Geometry terms are measured on the body scaled to 1.80 m (``scale = 1.80 / height``), so their weights mean
the same on every body:

- E_j2j (eq. 3): mean over the frame's contact pairs of ``|v_i - v_j|^2`` (m^2 at 1.80 m);
- E_int (eq. 4, our own form): ``sum_v (a_v / 1 cm^2) * sum_j w_vj * d_vj^2`` with ``d_vj`` the depth of vertex v
  inside segment j beyond its bind-pose depth (per-part SDF, :mod:`retarget_core.energy.sdf`), ``w_vj`` the
  geodesic ramp and ``a_v`` the vertex's area (m, m^2 at 1.80 m): the sum does not grow with the vertex count;
- E_foot (eq. 6): ``sum_{j in C} (|g_j(t) - g_j(t-1)|^2 + (y_j - y_j_rest)^2) / h_B`` over the foot joints in
  contact, heights above their rest height (the paper adds the rest heel height);
- E_weak (eq. 8): ``rho * sum_j |R(theta_B_j) - R(theta_A_j)|_F^2 + |o_B - o_A->B|^2`` (rotation matrices, as
  the paper's 9J rotation features);
- E_ee (eq. 9): ``sum_{j in ee} |gdot_B_j / h_B - gdot_A_j / h_A|^2``.
Velocities are per frame (``x(t) - x(t-1)``, zero at the first frame).
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.energy.sdf import REFERENCE_HEIGHT_M, PartSDF, effective_depth, sample_pairs
from retarget_core.energy.weights import EnergyWeights

UNIT_AREA_M2 = 1e-4  # 1 cm^2


def frame_velocity(x: Tensor) -> Tensor:
    """``x(t) - x(t-1)`` along the first dimension, zero at the first frame (same shape as ``x``)."""
    return torch.cat([torch.zeros_like(x[:1]), x[1:] - x[:-1]], dim=0)


def vertex_contact_energy(posed: Tensor, constraints: ContactConstraints, height: float) -> Tensor:
    """E_j2j ``(F,)`` for posed vertices ``(F, V, 3)``: mean squared distance of each frame's constrained
    pairs at 1.80 m scale; 0 in frames without constraints."""
    f_n = posed.shape[0]
    out = posed.new_zeros(f_n)
    if constraints.count == 0:
        return out
    s = REFERENCE_HEIGHT_M / height
    flat = posed.reshape(-1, 3)
    v_n = posed.shape[1]
    xi = flat.index_select(0, constraints.frame * v_n + constraints.i)
    xj = flat.index_select(0, constraints.frame * v_n + constraints.j)
    d2 = ((xi - xj) * s).pow(2).sum(-1)
    total = out.index_add(0, constraints.frame, d2)
    count = torch.zeros(f_n, dtype=posed.dtype).index_add(0, constraints.frame, torch.ones_like(d2))
    return total / count.clamp_min(1.0)


def interpenetration_energy(sdf: PartSDF, posed: Tensor, seg_mats: Tensor) -> Tensor:
    """E_int ``(F,)`` for posed vertices ``(F, V, 3)`` and segment transforms ``(F, S, 3, 4)``."""
    samples = sample_pairs(sdf, posed, seg_mats)
    s = sdf.scale_to_180
    depth = effective_depth(sdf, samples) * s
    area = sdf.vertex_area.to(posed.dtype).index_select(0, samples.vertex) * s * s / UNIT_AREA_M2
    return posed.new_zeros(posed.shape[0]).index_add(0, samples.frame, area * depth.pow(2))


def foot_energy(global_positions: Tensor, rest_positions: Tensor, contacts: FootContacts, height: float, ground: float = 0.0) -> Tensor:
    """E_foot ``(F,)`` from world joint positions ``(F, J, 3)``, rest positions ``(J, 3)`` standing on the
    ground and the contact labels of the source (``contacts.labels (F, 4)``)."""
    out = global_positions.new_zeros(global_positions.shape[0])
    for c, j in enumerate(contacts.joints):
        if j < 0:
            continue
        g = global_positions[:, j]
        vel2 = frame_velocity(g).pow(2).sum(-1)
        h2 = (g[:, 1] - ground - rest_positions[j, 1]).pow(2)
        out = out + contacts.labels[:, c].to(g.dtype) * (vel2 + h2) / height
    return out


def rotation_energy(target_rotations: Tensor, source_rotations: Tensor) -> Tensor:
    """``sum_j |R_B - R_A|_F^2`` ``(F,)`` of local rotations ``(F, J, 4)`` of corresponding joints."""
    diff = rot.to_matrix(target_rotations) - rot.to_matrix(source_rotations)
    return diff.pow(2).sum(dim=(-1, -2, -3))


def root_velocity_energy(target_root: Tensor, source_root: Tensor, leg_ratio: float) -> Tensor:
    """``|o_B - o_A->B|^2`` ``(F,)``: root positions ``(F, 3)`` of result and source; the source's velocity is
    scaled by the ratio of leg lengths (target / source)."""
    return (frame_velocity(target_root) - leg_ratio * frame_velocity(source_root)).pow(2).sum(-1)


def weak_energy(
    target_rotations: Tensor, source_rotations: Tensor, target_root: Tensor, source_root: Tensor, leg_ratio: float, rho: float
) -> Tensor:
    """E_weak ``(F,)`` (eq. 8)."""
    return rho * rotation_energy(target_rotations, source_rotations) + root_velocity_energy(target_root, source_root, leg_ratio)


def end_effector_energy(target_positions: Tensor, source_positions: Tensor, target_height: float, source_height: float) -> Tensor:
    """E_ee ``(F,)`` from world positions ``(F, E, 3)`` of the same end effectors on result and source."""
    vb = frame_velocity(target_positions) / target_height
    va = frame_velocity(source_positions) / source_height
    return (vb - va).pow(2).sum(dim=(-1, -2))


def total_energy(terms: dict[str, Tensor], weights: EnergyWeights) -> Tensor:
    """The weighted sum ``(F,)`` of the terms present in ``terms`` (keys: contact, interpenetration, foot,
    rotation, root, end_effector)."""
    total: Tensor | None = None
    for name, value in terms.items():
        w = getattr(weights, name)
        total = value * w if total is None else total + value * w
    if total is None:
        raise ValueError("no energy term given")
    return total


__all__ = [
    "end_effector_energy",
    "foot_energy",
    "frame_velocity",
    "interpenetration_energy",
    "root_velocity_energy",
    "rotation_energy",
    "total_energy",
    "vertex_contact_energy",
    "weak_energy",
]
