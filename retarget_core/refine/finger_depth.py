"""How deep fingers and palms are inside the rest of the body: what the finger clearance stage measures
(:mod:`retarget_core.refine.fingers`).

A vertex's depth is the collision stages' (:mod:`retarget_core.energy.sdf`): inside the parts a hand is tested
against (the job's part SDFs, blended), beyond the bind pose's depth, weighted by the geodesic ramp. A finger
*sinks* only where it is deeper than the palm of its hand by more than the stage's tolerance: a palm in the body
(a hand the contact stages rest on a thigh, or in the skinning fold at the hip on a walk) is the stages' before,
and no finger turn could lift it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.context import RefineContext
from retarget_core.energy.sdf import segment_distance, segment_matrices

if TYPE_CHECKING:
    from retarget_core.refine.fingers import FingerChain

CHUNK_FRAMES = 64  # frames posed at once when a whole clip is measured


@dataclass(frozen=True)
class FingerVertices:
    """The vertices a finger turn moves, and the palms. index: ``(N,)`` body vertices with skin weight on a turned
    finger joint; chain: ``(N,)`` the chain weighing most on it; own: ``(N,)`` its largest weight is on that chain
    (a finger vertex, else a palm vertex the finger drags); level: ``(N,)`` for a finger vertex the place of its
    dominant joint in the chain, for a dragged one the farthest place it is weighted to; palm: ``(P,)`` body
    vertices whose largest weight is on a hand or a metacarpal; palm_hand: ``(P,)`` their hand (an index into the
    chains' distinct hands); hand_of: ``(C,)`` each chain's hand (same index); tested: ``(S,)`` the segments a hand
    is tested against (with a grid)."""

    index: Tensor
    chain: Tensor
    own: Tensor
    level: Tensor
    palm: Tensor
    palm_hand: Tensor
    hand_of: Tensor
    tested: Tensor


def _palm_vertices(
    chains: list[FingerChain], dominant: Tensor, body: Tensor, num_joints: int
) -> tuple[Tensor, Tensor, Tensor]:
    """``(palm (P,), palm_hand (P,), hand_of (C,))`` of :class:`FingerVertices`, from each vertex's dominant joint
    ``dominant (V,)`` and the body mask ``body (V,)``."""
    hands = sorted({c.hand for c in chains})
    hand_of_joint = torch.full((num_joints,), -1, dtype=torch.long)
    for c in chains:
        hand_of_joint[[c.hand, c.base]] = hands.index(c.hand)
    palm_hand = hand_of_joint[dominant]
    palm = torch.nonzero((palm_hand >= 0) & body).flatten()
    return palm, palm_hand[palm], torch.tensor([hands.index(c.hand) for c in chains], dtype=torch.long)


def finger_vertices(ctx: RefineContext, chains: list[FingerChain]) -> FingerVertices:
    """The body vertices of every chain (:class:`retarget_core.refine.fingers.FingerChain`), the palms, and the
    segments they are tested against."""
    character, parts = ctx.target, ctx.parts
    chain_of = torch.full((character.skeleton.num_joints,), -1, dtype=torch.long)
    level_of = torch.full_like(chain_of, -1)
    for c, ch in enumerate(chains):
        chain_of[list(ch.joints)], level_of[list(ch.joints)] = c, torch.arange(len(ch.joints))
    joints, weights = character.skin_joints, character.skin_weights.clamp_min(0.0)
    owner = chain_of[joints]  # (V, K) chain of each influence, -1 for other joints
    share = weights.new_zeros(len(joints), len(chains) + 1).scatter_add_(1, owner + 1, weights)[:, 1:]  # (V, C)
    best, chain = share.max(1)
    dominant = joints.gather(1, weights.argmax(1, keepdim=True))[:, 0]
    own = chain_of[dominant] >= 0
    chain = torch.where(own, chain_of[dominant], chain)
    farthest = torch.where((owner == chain[:, None]) & (weights > 0), level_of[joints], -1).amax(1)
    level = torch.where(own, level_of[dominant], farthest)
    body = torch.ones_like(own) if parts.body is None else parts.body
    index = torch.nonzero((best > 0) & body).flatten()
    palm, palm_hand, hand_of = _palm_vertices(chains, dominant, body, character.skeleton.num_joints)
    has_grid = torch.tensor([g is not None for g in ctx.sdf.grids])
    tested = ctx.sdf.allowed.index_select(0, parts.vertex_part[index].unique()).any(0) & has_grid
    return FingerVertices(index, chain[index], own[index], level[index], palm, palm_hand, hand_of, tested)


def _overlap(ctx: RefineContext, posed: Tensor, group: Tensor, num_groups: int, mats: Tensor) -> Tensor:
    """``(F, G, S)``: the bounding box of group ``g``'s posed points meets segment ``s``'s posed grid box; ``posed
    (F, R, 3)`` points of groups ``group (R,)``, ``mats (F, S, 3, 4)`` the segments' skinning transforms."""
    corners = (
        torch.einsum("fsij,skj->fski", mats[..., :3], ctx.sdf.grid_corners().to(mats.dtype)) + mats[:, :, None, :, 3]
    )
    idx = group[None, :, None].expand_as(posed)
    lo = posed.new_full((posed.shape[0], num_groups, 3), math.inf).scatter_reduce(1, idx, posed, "amin")
    hi = posed.new_full((posed.shape[0], num_groups, 3), -math.inf).scatter_reduce(1, idx, posed, "amax")
    return (
        (lo[:, :, None] <= corners.max(2).values[:, None]) & (hi[:, :, None] >= corners.min(2).values[:, None])
    ).all(-1)


def depths(ctx: RefineContext, verts: Tensor, group: Tensor, tested: Tensor, grot: Tensor, gpos: Tensor,
           mats: Tensor | None = None, active: Tensor | None = None) -> Tensor:  # fmt: skip
    """Depth ``(F, R)`` (m, the body's scale) of the vertices ``verts (R,)`` inside the segments ``tested (S,)``
    their parts are tested against (module doc), for world transforms ``(F, J, 4)``, ``(F, J, 3)`` (``mats (F, S,
    3, 4)``: the segments' skinning transforms, when known). ``group (R,)``: the vertices are boxed by group (a
    finger, a palm) to skip the segments a group's box misses. Only points inside a segment's grid box are sampled
    (beyond it the distance exceeds the grid margin); ``active (F, G)``: where False, a group is not measured (0)."""
    sdf = ctx.sdf
    posed = ctx.target.pose_vertex_subset(verts, grot, gpos)  # (F, R, 3)
    out = posed.new_zeros(posed.shape[:2])
    if len(verts) == 0:
        return out
    mats = segment_matrices(ctx.target, ctx.parts, grot, gpos) if mats is None else mats
    allowed = sdf.allowed.index_select(0, ctx.parts.vertex_part.index_select(0, verts)) & tested  # (R, S)
    overlap = _overlap(ctx, posed, group, int(group.max()) + 1, mats)  # (F, G, S)
    overlap = overlap if active is None else overlap & active[:, : overlap.shape[1], None]
    corners = sdf.grid_corners()  # (S, 8, 3): the first is the box's low corner, the last its high one
    for s in torch.nonzero(overlap.any(1).any(0) & tested).flatten().tolist():
        fi, ri = torch.nonzero(overlap[:, :, s].index_select(1, group) & allowed[:, s], as_tuple=True)
        m = mats[:, s].index_select(0, fi)  # (P, 3, 4)
        local = torch.einsum("nji,nj->ni", m[..., :3], posed[fi, ri] - m[..., 3])  # in the segment's rest frame
        box = torch.nonzero(((local >= corners[s, 0]) & (local <= corners[s, -1])).all(-1)).flatten()
        if len(box) == 0:
            continue
        fi, ri, v = fi[box], ri[box], verts.index_select(0, ri[box])
        dist = segment_distance(sdf, s, local.index_select(0, box))
        depth = (-dist - sdf.rest_depth[v, s].to(dist.dtype)).clamp_min(0.0) * sdf.geodesic_weight[v, s].to(dist.dtype)
        out.index_put_((fi, ri), torch.maximum(out[fi, ri], depth.to(out.dtype)))
    return out


def finger_depths(ctx: RefineContext, fv: FingerVertices, rows: Tensor, grot: Tensor, gpos: Tensor,
                  mats: Tensor | None = None, active: Tensor | None = None) -> Tensor:  # fmt: skip
    """:func:`depths` ``(F, R)`` of the finger vertices ``fv.index[rows]``, boxed by chain (``active (F, C)``: the
    chains measured on each frame)."""
    verts, chain = fv.index.index_select(0, rows), fv.chain.index_select(0, rows)
    return depths(ctx, verts, chain, fv.tested, grot, gpos, mats, active)


def chain_depths(depth: Tensor, fv: FingerVertices, rows: Tensor, num_chains: int, level: int,
                 own: bool = True) -> Tensor:  # fmt: skip
    """Deepest vertex ``(F, C)`` of each chain from its ``level``-th joint on (``own``: its finger vertices, else
    the palm vertices it drags), from ``depth (F, R)`` of the vertices ``rows (R,)``."""
    chain, lvl = fv.chain.index_select(0, rows), fv.level.index_select(0, rows)
    mine = (lvl >= level) & (fv.own.index_select(0, rows) == own)
    out = depth.new_zeros(depth.shape[0], num_chains)
    return out.scatter_reduce(1, chain[mine].expand(depth.shape[0], -1), depth[:, mine], "amax")


def palm_depths(ctx: RefineContext, fv: FingerVertices, grot: Tensor, gpos: Tensor) -> Tensor:
    """Deepest palm vertex ``(F, C)`` of each chain's hand, for world transforms ``(F, J, 4)``, ``(F, J, 3)``."""
    depth = depths(ctx, fv.palm, fv.palm_hand, fv.tested, grot, gpos)  # (F, P)
    hands = int(fv.hand_of.max()) + 1
    per_hand = depth.new_zeros(depth.shape[0], hands)
    per_hand = per_hand.scatter_reduce(1, fv.palm_hand.expand(depth.shape[0], -1), depth, "amax")
    return per_hand.index_select(1, fv.hand_of)


def over_clip(ctx: RefineContext, local: Tensor, trans: Tensor, measure: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """``measure(grot, gpos)`` ``(F, ...)`` on frames ``local (F, J, 4)``, ``trans (F, J, 3)``, posed
    ``CHUNK_FRAMES`` at a time."""
    parts = [
        measure(
            *kinematics.forward_kinematics(
                ctx.target.skeleton.parents, local[s : s + CHUNK_FRAMES], trans[s : s + CHUNK_FRAMES]
            )
        )  # fmt: skip
        for s in range(0, local.shape[0], CHUNK_FRAMES)
    ]
    return torch.cat(parts) if parts else local.new_zeros(0)


def sinking(ctx: RefineContext, fv: FingerVertices, local: Tensor, trans: Tensor, num_chains: int, level: int = 0,
            chains: Tensor | None = None) -> Tensor:  # fmt: skip
    """Deepest vertex ``(F, C)`` (m, the body's scale) of every chain from its ``level``-th joint on, on frames
    ``local (F, J, 4)``, ``trans (F, J, 3)`` (``chains (C,)``: only these measured, the others 0)."""
    rows = torch.arange(len(fv.index)) if chains is None else torch.nonzero(chains[fv.chain]).flatten()
    return over_clip(ctx, local, trans,
                     lambda g, p: chain_depths(finger_depths(ctx, fv, rows, g, p), fv, rows, num_chains, level))  # fmt: skip


def palms(ctx: RefineContext, fv: FingerVertices, local: Tensor, trans: Tensor) -> Tensor:
    """:func:`palm_depths` ``(F, C)`` on frames ``local (F, J, 4)``, ``trans (F, J, 3)``."""
    return over_clip(ctx, local, trans, lambda g, p: palm_depths(ctx, fv, g, p))


__all__ = ["FingerVertices", "chain_depths", "depths", "finger_depths", "finger_vertices", "palms",
           "sinking"]  # fmt: skip
