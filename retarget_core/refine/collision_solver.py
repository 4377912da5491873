"""The collision stage's solver: the energy of the residual knots over a set of terms, and Adam on the knots
with the colliding triples re-selected every few steps."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.refine.collision_energy import (
    contact_energy,
    near_contact_rows,
    near_triples,
    pair_energy,
    penetration_energy,
)
from retarget_core.refine.collision_mesh import mesh_energy
from retarget_core.refine.collision_params import CollisionParams
from retarget_core.refine.collision_problem import Problem
from retarget_core.refine.collision_terms import Terms, compact
from retarget_core.refine.context import RefineContext


def expmap(r: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` xyzw of rotation vectors ``(..., 3)``, smooth at zero."""
    theta = (r.pow(2).sum(-1, keepdim=True) + 1e-12).sqrt()
    return torch.cat([r * (torch.sin(0.5 * theta) / theta), torch.cos(0.5 * theta)], dim=-1)


def apply_residual(rot_in: Tensor, joints: list[int], resid: Tensor) -> Tensor:
    """Quaternions ``rot_in (F, J, 4)`` with ``rot_in[:, joints] * exp(resid (F, Jo, 3))``."""
    out = rot_in.clone()
    out[:, joints] = rot.mul(rot_in[:, joints], expmap(resid))
    return out




def energy(ctx: RefineContext, prob: Problem, terms: Terms, knots: Tensor, params: CollisionParams,
            scale: float) -> tuple[Tensor, dict[str, Tensor]]:  # fmt: skip
    """Total energy of the knots ``(N, Jo, 3)`` and its terms."""
    posed, seg_mats, gpos = terms.poser(prob.local(knots), prob.trans)
    ee = (gpos.index_select(1, prob.ee_joints) - prob.ee_in) * (100.0 * scale)
    parts = {
        "penetration": params.w_penetration * penetration_energy(ctx.sdf, terms.triples, posed, seg_mats, scale),
        "contact": params.w_contact * contact_energy(ctx.sdf, terms.targets, posed, seg_mats, scale,
                                                      params.contact_gap_m / scale),
        "contact_pairs": params.w_pair * pair_energy(terms.pairs, posed, scale, params.pair_allowance_m / scale),
        "mesh": params.w_mesh * mesh_energy(terms.mesh, posed, scale, params.clearance_m / scale),
        "end_effector": (ee.pow(2).sum(-1) * prob.ee_weight).sum(),
        "ground": params.w_ground * ((terms.ground.floor - posed[:, terms.ground.point, 1]).clamp(min=0.0) * (100.0 * scale)).pow(2).sum(),
        "identity": params.w_identity * (knots.pow(2).sum(-1) * prob.stiffness).sum(),
        "smooth": params.w_smooth * (knots[2:] - 2 * knots[1:-1] + knots[:-2]).pow(2).sum(),
    }
    return sum(parts.values(), knots.new_zeros(())), parts


def optimise(ctx: RefineContext, prob: Problem, terms: Terms, knots: Tensor, steps: int, lr: float,
              params: CollisionParams, scale: float, within_m: float | None = None,
              free: Tensor | None = None) -> dict[str, float]:  # fmt: skip
    """Adam on ``knots`` in place (cosine-decayed step size; only the knots ``free (N,)`` bool when given); the
    last energy terms. Every ``recull_every`` steps only the triples within ``within_m`` (default
    ``recull_within_m``) are kept."""
    within = (params.recull_within_m if within_m is None else within_m) / scale
    knots.requires_grad_(True)
    opt = torch.optim.Adam([knots], lr=lr)
    last: dict[str, Tensor] = {}
    full, full_terms = terms.triples, terms
    for it in range(steps):
        if it % params.recull_every == 0:
            with torch.no_grad():
                posed, seg_mats, _ = full_terms.poser(prob.local(knots), prob.trans)
            near = near_triples(ctx.sdf, full, posed, seg_mats, within)
            targets = near_contact_rows(ctx.sdf, full_terms.targets, posed, seg_mats, within)
            terms = compact(ctx, Terms(full_terms.poser, near, targets, full_terms.pairs, full_terms.mesh,
                                         full_terms.ground))  # fmt: skip
        frac = it / max(steps - 1, 1)
        decay = params.lr_final_fraction + (1 - params.lr_final_fraction) * 0.5 * (1 + math.cos(math.pi * frac))
        for g in opt.param_groups:
            g["lr"] = lr * decay
        total, last = energy(ctx, prob, terms, knots, params, scale)
        opt.zero_grad()
        total.backward()
        if free is not None and knots.grad is not None:
            knots.grad[~free] = 0.0  # Adam's moments stay zero there: those knots do not move
        opt.step()
    knots.requires_grad_(False)
    return {k: float(v.detach()) for k, v in last.items()}




__all__ = ["apply_residual", "energy", "expmap", "optimise"]
