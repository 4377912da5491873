"""The collision stage's solver: the energy of the residual knots over a set of terms, and Adam on the knots
with the colliding triples re-selected every few steps."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.context import RefineContext
from retarget_core.geometry.triples import near_triples, penetration_energy_rows
from retarget_core.refine.collision_energy import (
    contact_distances_rows,
    contact_energy_rows,
    near_contact_rows,
    pair_energy_rows,
)
from retarget_core.refine.collision_mesh import mesh_energy_rows
from retarget_core.refine.collision_params import CollisionParams
from retarget_core.refine.collision_problem import Problem
from retarget_core.refine.collision_terms import EnergyRows, Terms, compact, energy_rows, near_ground, read_rows


def expmap(r: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` xyzw of rotation vectors ``(..., 3)``, smooth at zero."""
    theta = (r.pow(2).sum(-1, keepdim=True) + 1e-12).sqrt()
    return torch.cat([r * (torch.sin(0.5 * theta) / theta), torch.cos(0.5 * theta)], dim=-1)


def apply_residual(rot_in: Tensor, joints: list[int], resid: Tensor) -> Tensor:
    """Quaternions ``rot_in (F, J, 4)`` with ``rot_in[:, joints] * exp(resid (F, Jo, 3))``."""
    out = rot_in.clone()
    out[:, joints] = rot.mul(rot_in[:, joints], expmap(resid))
    return out




def energy(ctx: RefineContext, prob: Problem, terms: Terms, rows: EnergyRows, knots: Tensor, params: CollisionParams,
           scale: float) -> tuple[Tensor, dict[str, Tensor]]:  # fmt: skip
    """Total energy of the knots ``(N, Jo, 3)`` and its terms; only the ``rows`` of ``terms`` are posed."""
    mats, gpos = terms.poser.transforms(prob.local(knots), prob.trans)
    xs, ms = read_rows(rows, mats)
    n_t = len(terms.triples.groups)
    n_c = len(ms) - n_t
    d, d_rows, _ = contact_distances_rows(ctx.sdf, terms.targets, xs[n_t : n_t + n_c], ms[n_t:])
    xi, xj, xm, a, b, c, xg = xs[n_t + n_c :]
    ee = (gpos.index_select(1, prob.ee_joints) - prob.ee_in) * (100.0 * scale)
    parts = {
        "penetration": params.w_penetration * penetration_energy_rows(ctx.sdf, terms.triples, xs[:n_t], ms[:n_t], scale),
        "contact": params.w_contact * contact_energy_rows(terms.targets, d, d_rows, scale, params.contact_gap_m / scale),
        "contact_pairs": params.w_pair * pair_energy_rows(terms.pairs, xi, xj, scale, params.pair_allowance_m / scale),
        "mesh": params.w_mesh * mesh_energy_rows(terms.mesh, xm, a, b, c, scale, params.clearance_m / scale),
        "end_effector": (ee.pow(2).sum(-1) * prob.ee_weight).sum(),
        "ground": params.w_ground * ((terms.ground.floor - xg[:, 1]).clamp(min=0.0) * (100.0 * scale)).pow(2).sum(),
        "identity": params.w_identity * (knots.pow(2).sum(-1) * prob.stiffness).sum(),
        "smooth": params.w_smooth * (knots[2:] - 2 * knots[1:-1] + knots[:-2]).pow(2).sum(),
    }
    return sum(parts.values(), knots.new_zeros(())), parts


def recull(ctx: RefineContext, prob: Problem, full: Terms, knots: Tensor, within: float,
           ground_within: float) -> tuple[Terms, EnergyRows]:  # fmt: skip
    """The terms that can become non-zero in the next few steps at the knots' pose (triples and contact rows
    within ``within``, floor rows within ``ground_within``, m), compacted, and the rows they read."""
    with torch.no_grad():
        posed, seg_mats, _ = full.poser(prob.local(knots), prob.trans)
    near = near_triples(ctx.sdf, full.triples, posed, seg_mats, within)
    targets = near_contact_rows(ctx.sdf, full.targets, posed, seg_mats, within)
    ground = near_ground(full.ground, posed, ground_within)
    terms = compact(ctx, Terms(full.poser, near, targets, full.pairs, full.mesh, ground))
    return terms, energy_rows(terms, prob.local_in.shape[1])


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
    full = terms
    for it in range(steps):
        if it % params.recull_every == 0:
            terms, rows = recull(ctx, prob, full, knots, within, params.candidate_slack_m / scale)
        frac = it / max(steps - 1, 1)
        decay = params.lr_final_fraction + (1 - params.lr_final_fraction) * 0.5 * (1 + math.cos(math.pi * frac))
        for g in opt.param_groups:
            g["lr"] = lr * decay
        total, last = energy(ctx, prob, terms, rows, knots, params, scale)
        opt.zero_grad()
        total.backward()
        if free is not None and knots.grad is not None:
            knots.grad[~free] = 0.0  # Adam's moments stay zero there: those knots do not move
        opt.step()
    knots.requires_grad_(False)
    return {k: float(v.detach()) for k, v in last.items()}


__all__ = ["apply_residual", "energy", "expmap", "optimise"]
