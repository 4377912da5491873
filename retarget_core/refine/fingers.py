"""Finger clearance: fingers resting on the body are turned onto its surface, not into it.

The copy sets every finger joint from the source (docs/mapping.md) and the other refinement stages turn only the
22 canonical joints, so a hand that the contact stages put on a thicker thigh keeps the copy's finger angles, and
its fingers (most often the thumb, whose base is part of the palm) can end inside the thigh. This stage runs last
and turns finger joints only, and only where finger vertices are inside another part of the body:

1. Find: every finger vertex's depth inside the parts a hand is tested against, on every frame (the job's part
   SDFs, blended, beyond the bind pose's depth and weighted by the geodesic ramp: the depth the collision stages
   use, :mod:`retarget_core.energy.sdf`). Frames where no finger is deeper than ``tolerance_m`` keep the copy's
   finger rotations bit for bit, and so does every finger that does not sink.
2. Turn, proximal to distal (first, middle, last joint of each finger and of the thumb): on the frames where a
   finger sinks from that joint on, each candidate turn of the joint is measured (on rays from no turn, every
   ``step_deg`` up to ``max_turn_deg``: flexion and extension for a hinge, ``directions`` rays in the
   flexion-spread plane for the thumb's first joint); a ray "clears" a frame at the smallest turn along it that
   takes the finger to the least depth any candidate inside the joint's range reaches, plus ``tolerance_m``. Per
   finger and run of such frames one ray is kept (the one whose worst frame needs the least turn), so the finger
   does not flip between solutions from frame to frame; the turn along it is eased in and out over
   ``ease_seconds`` each side (a running maximum, then a binomial average: never less than a frame needs, never
   beyond the joint's range on the frames measured). The segments beyond follow (their local rotations are kept), so a knuckle that lifts the whole
   finger leaves nothing for the next joint. Palm, wrist and body do not move: the palm's contact is what the
   contact stages made it.

Axes. Palm normal ``n``: ``d x k`` on the left hand, ``k x d`` on the right, with ``d`` from the wrist to the mean
of the fingers' first joints and ``k`` the knuckle line from pinky to index. Flexion axis: the hand's ``d x n`` for
the four fingers, a thumb's own first bone x ``n``; a positive turn flexes (toward the palm). Finger joints turn
about their flexion axis only (hinges: their side-to-side spread is left alone, so fingers never cross); the
thumb's first joint (its saddle joint, CMC) also spreads, about ``bone x flexion axis``. A joint's bend is the
signed angle about its flexion axis from the previous bone (wrist or metacarpal to knuckle, for the first joint).

Ranges (degrees, extension negative; active ranges of motion of clinical tables, AAOS): fingers -30..90 at the
knuckle (MCP), -5..100 (PIP), -10..80 (DIP); thumb -20..45 (CMC), -10..60 (MCP), -20..80 (IP); the thumb's CMC
spreads at most ``THUMB_SPREAD_DEG`` either way from the copy. A joint the copy left outside its range may turn
back toward it, never further out.

Lengths are given at a 1.80 m character and scaled to the body. The stage computes on the CPU and returns the
motion on the device it came on.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.canonical import FINGERS, JointMapping
from retarget_core.context import RefineContext, StageOutcome
from retarget_core.energy.sdf import segment_distance, segment_matrices
from retarget_core.motion import Motion
from retarget_core.refine.two_bone_ik import axis_angle
from retarget_core.skeleton import Skeleton

REFERENCE_HEIGHT_M = 1.80
SIDES: tuple[str, ...] = ("Left", "Right")
SEGMENTS: tuple[int, ...] = (1, 2, 3)  # the joints turned, proximal first (a metacarpal, 0, stays with the palm)
FINGER_RANGE_DEG: tuple[tuple[float, float], ...] = ((-30.0, 90.0), (-5.0, 100.0), (-10.0, 80.0))
THUMB_RANGE_DEG: tuple[tuple[float, float], ...] = ((-20.0, 45.0), (-10.0, 60.0), (-20.0, 80.0))
THUMB_SPREAD_DEG = 40.0  # the thumb's CMC spread either way from the copy; every other joint is a hinge here
MIN_AXIS = 0.3  # a thumb bone this close to the palm normal (|bone x n|) flexes about the hand's axis instead


@dataclass(frozen=True)
class FingerParams:
    """Settings (lengths at a 1.80 m character)."""

    # Depth a finger may keep: below it a finger is on the surface (about the SDF grids' trilinear error).
    tolerance_m: float = 0.001
    # Candidate turns: every step_deg up to max_turn_deg along each ray; rays around a joint that also spreads.
    max_turn_deg: float = 45.0
    step_deg: float = 2.5
    directions: int = 12
    # Turns are eased in and out over this long each side of the frames that need them (and never drop between).
    ease_seconds: float = 0.2
    # Frames measured at once (each carries every candidate: memory is candidates x frames x finger vertices).
    frame_chunk: int = 8


@dataclass(frozen=True)
class FingerChain:
    """One finger of one hand. joints: its turned joints, proximal first (at most 3); base: the joint its first
    bone starts from (metacarpal, else hand); hand: the hand joint; bone: ``(K, 3)`` each joint's bone direction
    in its own rest frame; flex: ``(K, 2)`` bend range (degrees); spread: ``(K,)`` largest spread either way."""

    side: str
    finger: str
    joints: tuple[int, ...]
    base: int
    hand: int
    bone: Tensor
    flex: Tensor
    spread: Tensor

    @property
    def thumb(self) -> bool:
        return self.finger == "Thumb"


def _rest_bone(sk: Skeleton, joints: list[int], k: int, pos: Tensor) -> Tensor:
    """Rest direction ``(3,)`` of ``joints[k]``'s bone: to the next joint of the chain, else to its longest child,
    else continuing the previous bone."""
    j = joints[k]
    ends = (
        [joints[k + 1]]
        if k + 1 < len(joints)
        else sorted(sk.children(j), key=lambda c: -float((pos[c] - pos[j]).norm()))
    )
    for e in ends:
        if float((pos[e] - pos[j]).norm()) > 1e-4:
            return pos[e] - pos[j]
    return pos[j] - pos[sk.parents[j]]


def finger_chains(sk: Skeleton, mapping: JointMapping) -> list[FingerChain]:
    """Every mapped finger with at least its first joint (thumbs included), of hands with two fingers or more
    besides the thumb (a palm normal needs them: a hand with fewer keeps the copy's fingers)."""
    grot, pos = sk.rest_global()
    chains = []
    for side, finger in itertools.product(SIDES, FINGERS):
        hand = mapping.joints.get(f"{side}Hand")
        joints = [mapping.extras[n] for k in SEGMENTS if (n := f"{side}Hand{finger}{k}") in mapping.extras]
        if hand is None or f"{side}Hand{finger}1" not in mapping.extras:
            continue
        bone = torch.stack([rot.apply(rot.inv(grot[j]), _rest_bone(sk, joints, k, pos)) for k, j in enumerate(joints)])
        thumb = finger == "Thumb"
        flex = torch.tensor((THUMB_RANGE_DEG if thumb else FINGER_RANGE_DEG)[: len(joints)])
        spread = torch.zeros(len(joints))
        spread[0] = THUMB_SPREAD_DEG if thumb else 0.0
        base = mapping.extras.get(f"{side}Hand{finger}0", hand)
        chains.append(
            FingerChain(side, finger, tuple(joints), base, hand, bone / bone.norm(dim=-1, keepdim=True), flex, spread)
        )
    return [c for c in chains if sum(m.side == c.side and not m.thumb for m in chains) >= 2]


def _unit(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _bone(chain: FingerChain, k: int, grot: Tensor) -> Tensor:
    """World direction ``(F, 3)`` of the chain's ``k``-th bone."""
    return rot.apply(grot[:, chain.joints[k]], chain.bone[k].to(grot.dtype).expand(grot.shape[0], 3))


def chain_axes(chains: list[FingerChain], level: int, grot: Tensor, gpos: Tensor) -> tuple[Tensor, Tensor]:
    """World flexion and spread axes ``(F, C, 3)`` of every chain's ``level``-th joint (module doc), from world
    transforms ``(F, J, 4)``, ``(F, J, 3)``; a chain without that joint gets its first joint's."""
    flex, spread = [], []
    for c in chains:
        mates = [m for m in chains if m.side == c.side and not m.thumb]
        d = torch.stack([gpos[:, m.joints[0]] for m in mates]).mean(0) - gpos[:, c.hand]
        k = gpos[:, mates[0].joints[0]] - gpos[:, mates[-1].joints[0]]  # index side minus pinky side
        n = _unit(torch.cross(d, k, dim=-1) if c.side == "Left" else torch.cross(k, d, dim=-1))
        axis = _unit(torch.cross(d, n, dim=-1))
        bone = _bone(c, min(level, len(c.joints) - 1), grot)
        if c.thumb:
            own = torch.cross(_bone(c, 0, grot), n, dim=-1)
            axis = torch.where(own.norm(dim=-1, keepdim=True) > MIN_AXIS, _unit(own), axis)
        flex.append(axis)
        spread.append(_unit(torch.cross(bone, axis, dim=-1)))
    return torch.stack(flex, dim=1), torch.stack(spread, dim=1)


def bends(chains: list[FingerChain], level: int, grot: Tensor, gpos: Tensor, flex: Tensor) -> Tensor:
    """Bend ``(F, C)`` (degrees, flexion positive) of every chain's ``level``-th joint about ``flex (F, C, 3)``
    (0 for a chain without that joint)."""
    out = []
    for c, chain in enumerate(chains):
        if level >= len(chain.joints):
            out.append(torch.zeros(grot.shape[0], dtype=grot.dtype))
            continue
        prev = gpos[:, chain.joints[0]] - gpos[:, chain.base] if level == 0 else _bone(chain, level - 1, grot)
        own = _bone(chain, level, grot)
        sin = (torch.cross(prev, own, dim=-1) * flex[:, c]).sum(-1)
        out.append(torch.rad2deg(torch.atan2(sin, (prev * own).sum(-1))))
    return torch.stack(out, dim=1)


@dataclass(frozen=True)
class FingerVertices:
    """The vertices a finger turn moves. index: ``(N,)`` body vertices with skin weight on a turned finger joint;
    chain: ``(N,)`` the chain weighing most on it; own: ``(N,)`` its largest weight is on that chain (a finger
    vertex, else a palm vertex the finger drags); level: ``(N,)`` for a finger vertex the place of its dominant
    joint in the chain, for a dragged one the farthest place it is weighted to; tested: ``(S,)`` the segments a
    hand is tested against (with a grid)."""

    index: Tensor
    chain: Tensor
    own: Tensor
    level: Tensor
    tested: Tensor


def finger_vertices(ctx: RefineContext, chains: list[FingerChain]) -> FingerVertices:
    """The body vertices of every chain, and the segments they are tested against."""
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
    mine = best > 0 if parts.body is None else (best > 0) & parts.body
    index = torch.nonzero(mine).flatten()
    has_grid = torch.tensor([g is not None for g in ctx.sdf.grids])
    tested = ctx.sdf.allowed.index_select(0, parts.vertex_part[index].unique()).any(0) & has_grid
    return FingerVertices(index, chain[index], own[index], level[index], tested)


def _overlap(ctx: RefineContext, posed: Tensor, chain: Tensor, num_chains: int, mats: Tensor) -> Tensor:
    """``(F, C, S)``: the bounding box of chain ``c``'s posed points meets segment ``s``'s posed grid box; ``posed
    (F, R, 3)`` points of chains ``chain (R,)``, ``mats (F, S, 3, 4)`` the segments' skinning transforms."""
    corners = (
        torch.einsum("fsij,skj->fski", mats[..., :3], ctx.sdf.grid_corners().to(mats.dtype)) + mats[:, :, None, :, 3]
    )
    idx = chain[None, :, None].expand_as(posed)
    lo = posed.new_full((posed.shape[0], num_chains, 3), math.inf).scatter_reduce(1, idx, posed, "amin")
    hi = posed.new_full((posed.shape[0], num_chains, 3), -math.inf).scatter_reduce(1, idx, posed, "amax")
    return (
        (lo[:, :, None] <= corners.max(2).values[:, None]) & (hi[:, :, None] >= corners.min(2).values[:, None])
    ).all(-1)


def depths(ctx: RefineContext, fv: FingerVertices, rows: Tensor, grot: Tensor, gpos: Tensor,
           mats: Tensor | None = None) -> Tensor:  # fmt: skip
    """Depth ``(F, R)`` (m, the body's scale) of the finger vertices ``fv.index[rows]`` inside the segments they
    are tested against (the collision stages' depth: module doc), for world transforms ``(F, J, 4)``, ``(F, J, 3)``
    (``mats (F, S, 3, 4)``: the segments' skinning transforms, when known). Only points inside a segment's grid box
    are sampled (beyond it the distance exceeds the grid margin)."""
    sdf, verts, chain = ctx.sdf, fv.index.index_select(0, rows), fv.chain.index_select(0, rows)
    posed = ctx.target.pose_vertex_subset(verts, grot, gpos)  # (F, R, 3)
    mats = segment_matrices(ctx.target, ctx.parts, grot, gpos) if mats is None else mats
    allowed = sdf.allowed.index_select(0, ctx.parts.vertex_part.index_select(0, verts)) & fv.tested  # (R, S)
    overlap = _overlap(ctx, posed, chain, int(fv.chain.max()) + 1, mats)  # (F, C, S)
    corners = sdf.grid_corners()  # (S, 8, 3): the first is the box's low corner, the last its high one
    out = posed.new_zeros(posed.shape[:2])
    for s in torch.nonzero(overlap.any(1).any(0) & fv.tested).flatten().tolist():
        fi, ri = torch.nonzero(overlap[:, :, s].index_select(1, chain) & allowed[:, s], as_tuple=True)
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


def chain_depths(depth: Tensor, fv: FingerVertices, rows: Tensor, num_chains: int, level: int,
                 own: bool = True) -> Tensor:  # fmt: skip
    """Deepest vertex ``(F, C)`` of each chain from its ``level``-th joint on (``own``: its finger vertices, else
    the palm vertices it drags), from ``depth (F, R)`` of the vertices ``rows (R,)``."""
    chain, lvl = fv.chain.index_select(0, rows), fv.level.index_select(0, rows)
    mine = (lvl >= level) & (fv.own.index_select(0, rows) == own)
    out = depth.new_zeros(depth.shape[0], num_chains)
    return out.scatter_reduce(1, chain[mine].expand(depth.shape[0], -1), depth[:, mine], "amax")


def turned(local: Tensor, grot: Tensor, chains: list[FingerChain], level: int, axes: tuple[Tensor, Tensor],
           angle: Tensor) -> Tensor:  # fmt: skip
    """``local (F, J, 4)`` with each chain's ``level``-th joint turned in the world by ``angle (F, C, 2)`` (radians:
    flexion, spread) about ``axes`` (flexion and spread axes, ``(F, C, 3)`` each); ``grot (F, J, 4)`` the world
    rotations of ``local``. Untouched where both angles are 0."""
    out = local.clone()
    for c, chain in enumerate(chains):
        if level >= len(chain.joints):
            continue
        j = chain.joints[level]
        back = rot.inv(grot[:, j])  # world axes into the joint's own frame: G' = R_flex R_spread G
        flex = axis_angle(rot.apply(back, axes[0][:, c]), angle[:, c, 0])
        spread = axis_angle(rot.apply(back, axes[1][:, c]), angle[:, c, 1])
        q = rot.normalize(rot.mul(local[:, j], rot.mul(flex, spread)))
        out[:, j] = torch.where((angle[:, c] != 0).any(-1, keepdim=True), q, local[:, j])
    return out


def feasible(chains: list[FingerChain], level: int, bend: Tensor, turns: Tensor) -> Tensor:
    """``(M, F, C)``: turns ``turns (M, F, C, 2)`` (degrees: flexion, spread) keep the joint in its range, or no
    further out than its bend ``bend (F, C)`` already is; always for no turn; never for a chain without a
    ``level``-th joint."""
    has = torch.tensor([level < len(c.joints) for c in chains])
    k = [min(level, len(c.joints) - 1) for c in chains]
    lo = torch.tensor([float(c.flex[i, 0]) for c, i in zip(chains, k, strict=True)], dtype=bend.dtype)
    hi = torch.tensor([float(c.flex[i, 1]) for c, i in zip(chains, k, strict=True)], dtype=bend.dtype)
    spread = torch.tensor([float(c.spread[i]) for c, i in zip(chains, k, strict=True)], dtype=bend.dtype)

    def outside(b: Tensor) -> Tensor:
        return (lo - b).clamp_min(0.0) + (b - hi).clamp_min(0.0)

    ok = (outside(bend[None] + turns[..., 0]) <= outside(bend)[None]) & (turns[..., 1].abs() <= spread) & has
    return ok | (turns == 0).all(-1)


@dataclass
class LevelPose:
    """Frames at one level: ``local (n, J, 4)``, ``trans (n, J, 3)``, their world transforms, the chains' axes
    (flexion, spread ``(n, C, 3)``) and bends ``(n, C)`` at that level, and the finger vertex rows measured."""

    level: int
    local: Tensor
    trans: Tensor
    grot: Tensor
    gpos: Tensor
    axes: tuple[Tensor, Tensor]
    bend: Tensor
    rows: Tensor


def subtree_fk(
    sk: Skeleton, roots: list[int], local: Tensor, trans: Tensor, grot: Tensor, gpos: Tensor
) -> tuple[Tensor, Tensor]:
    """World rotations and positions ``(B, J, 4)``, ``(B, J, 3)`` after ``local (B, J, 4)`` changed at ``roots`` only:
    ``grot``, ``gpos`` (the transforms before) with the joints at and below ``roots`` recomputed."""
    below = set(roots)
    for j, p in enumerate(sk.parents):  # parents come first: one pass collects every descendant
        if p in below:
            below.add(j)
    grot, gpos = grot.clone(), gpos.clone()
    for j in sorted(below):
        p = sk.parents[j]
        grot[:, j] = rot.mul(grot[:, p], local[:, j])
        gpos[:, j] = gpos[:, p] + rot.apply(grot[:, p], trans[:, j])
    return grot, gpos


def level_pose(ctx: RefineContext, chains: list[FingerChain], level: int, local: Tensor, trans: Tensor,
               rows: Tensor) -> LevelPose:  # fmt: skip
    """The :class:`LevelPose` of frames ``local (n, J, 4)``, ``trans (n, J, 3)``."""
    grot, gpos = kinematics.forward_kinematics(ctx.target.skeleton.parents, local, trans)
    axes = chain_axes(chains, level, grot, gpos)
    return LevelPose(level, local, trans, grot, gpos, axes, bends(chains, level, grot, gpos, axes[0]), rows)


@dataclass(frozen=True)
class Candidates:
    """Candidate turns on rays from no turn: ``dirs (D, 2)`` unit directions in the (flexion, spread) plane,
    ``radii (R,)`` degrees from 0; ``turns`` ``(D * R, 2)``, direction-major."""

    dirs: Tensor
    radii: Tensor

    @property
    def turns(self) -> Tensor:
        return (self.dirs[:, None, :] * self.radii[None, :, None]).reshape(-1, 2)


def candidates(params: FingerParams, spread: bool) -> Candidates:
    """Flexion and extension alone for a hinge; ``params.directions`` rays around the plane where the joint also
    spreads."""
    n = params.directions if spread else 2
    psi = 2.0 * math.pi * torch.arange(n, dtype=torch.float64) / n
    dirs = torch.stack([psi.cos(), psi.sin()], -1)
    dirs = torch.where(dirs.abs() < 1e-9, 0.0, dirs).float()  # exact zeros: a hinge's rays never spread
    steps = round(params.max_turn_deg / params.step_deg)
    return Candidates(dirs, params.step_deg * torch.arange(steps + 1, dtype=torch.float32))


@dataclass
class Needs:
    """Per ray, frame and chain ``(D, n, C)`` (degrees): ``clear`` the smallest turn along the ray that takes the
    finger to the least depth any feasible candidate reaches plus the tolerance (inf: none does), ``least`` the
    turn of least depth along it, ``cap`` the largest turn up to which every turn along it is feasible: inside the
    joint's range, dragging no palm vertex deeper than no turn does, by more than the tolerance."""

    clear: Tensor
    least: Tensor
    cap: Tensor


def needs(ctx: RefineContext, fv: FingerVertices, chains: list[FingerChain], pose: LevelPose, cand: Candidates,
          tol: float) -> Needs:  # fmt: skip
    """Every candidate turn of every chain's ``pose.level``-th joint on ``pose``'s frames, measured (``tol``: m)."""
    (n, c_n), (d_n, r_n) = pose.bend.shape, (len(cand.dirs), len(cand.radii))
    turns = cand.turns.to(pose.local.dtype)[:, None, None, :].expand(-1, n, c_n, 2)  # (M, n, C, 2)
    rep = (len(turns), 1, 1)
    local = turned(pose.local.repeat(rep), pose.grot.repeat(rep), chains, pose.level,
                   (pose.axes[0].repeat(rep), pose.axes[1].repeat(rep)), torch.deg2rad(turns).reshape(-1, c_n, 2))  # fmt: skip
    roots = [c.joints[pose.level] for c in chains if pose.level < len(c.joints)]
    grot, gpos = subtree_fk(ctx.target.skeleton, roots, local, pose.trans.repeat(rep), pose.grot.repeat(rep),
                            pose.gpos.repeat(rep))  # fmt: skip
    mats = segment_matrices(ctx.target, ctx.parts, pose.grot, pose.gpos).repeat(
        len(turns), 1, 1, 1
    )  # no finger moves one
    every = depths(ctx, fv, pose.rows, grot, gpos, mats)
    depth, dragged = (chain_depths(every, fv, pose.rows, c_n, pose.level, own).view(d_n, r_n, n, c_n)
                      for own in (True, False))  # fmt: skip
    ok = feasible(chains, pose.level, pose.bend, turns).view(d_n, r_n, n, c_n) & (dragged <= dragged[:1, :1] + tol)
    ok = ok.cumprod(1).bool()  # along a ray, up to its first infeasible turn
    floor = depth.masked_fill(~ok, math.inf).amin((0, 1))
    radius = cand.radii.to(depth.dtype)[None, :, None, None].expand_as(depth)
    clear = radius.masked_fill(~(ok & (depth <= floor + tol)), math.inf).amin(1)
    least = cand.radii.to(depth.dtype)[depth.masked_fill(~ok, math.inf).argmin(1)]
    return Needs(clear, least, radius.masked_fill(~ok, -math.inf).amax(1))


def choose(found: Needs, frames: Tensor, gap: int) -> tuple[Tensor, Tensor]:
    """One ray per chain and run of frames (``frames (n,)`` split where more than ``gap`` apart): the one whose
    worst frame needs the least turn (a ray clearing every frame first). Returns the ray ``(n, C)`` and the turn
    along it ``(n, C)`` (degrees: the clearing one, else the least deep)."""
    ray = torch.zeros(found.clear.shape[1:], dtype=torch.long)
    cut = torch.nonzero(frames.diff() > gap).flatten() + 1
    for run in torch.tensor_split(torch.arange(len(frames)), cut.tolist()):
        need = found.clear[:, run]  # (D, r, C)
        misses = torch.isinf(need).sum(1)
        worst = need.masked_fill(torch.isinf(need), 0.0).amax(1)
        ray[run] = (misses * 1e4 + worst).argmin(0)[None]
    pick = ray[None]
    clear, least = found.clear.gather(0, pick)[0], found.least.gather(0, pick)[0]
    return ray, torch.where(torch.isinf(clear), least, clear)


def ease_frames(params: FingerParams, fps: float) -> int:
    """Half-width of the running maximum and of the average that ease a turn: together ``ease_seconds``."""
    return max(1, round(0.5 * params.ease_seconds * fps))


def dilate_smooth(x: Tensor, half: int) -> Tensor:
    """``x (F, C)`` dilated (a maximum over ``half`` frames each side), then averaged by a binomial kernel of the same
    half-width: smooth in time and never below ``x``."""
    if half <= 0:
        return x
    padded = torch.nn.functional.pad(x.T[:, None], (half, half), mode="replicate")
    wide = torch.nn.functional.max_pool1d(padded, 2 * half + 1, stride=1)
    kernel = torch.tensor([math.comb(2 * half, k) for k in range(2 * half + 1)], dtype=x.dtype)
    padded = torch.nn.functional.pad(wide, (half, half), mode="replicate")
    return torch.nn.functional.conv1d(padded, (kernel / kernel.sum())[None, None])[:, 0].T


def solve_level(ctx: RefineContext, fv: FingerVertices, chains: list[FingerChain], level: int, motion: Motion,
                params: FingerParams, depth: Tensor) -> Tensor:  # fmt: skip
    """Turns ``(F, C, 2)`` (degrees: flexion, spread) of every chain's ``level``-th joint over the clip (module doc):
    measured on the frames where a finger sinks from that joint on (``depth (F, C)``: its depth, m), one ray per
    run of them, eased in and out."""
    tol = params.tolerance_m * ctx.target.height / REFERENCE_HEIGHT_M
    local, trans = motion.rotations, motion.translations
    deep = depth > tol  # (F, C)
    frames = torch.nonzero(deep.any(1)).flatten()
    turns = local.new_zeros(local.shape[0], len(chains), 2)
    if len(frames) == 0:
        return turns
    rows = torch.nonzero(deep.any(0).index_select(0, fv.chain)).flatten()  # vertices of the sinking chains
    cand = candidates(params, any(level < len(c.joints) and float(c.spread[level]) > 0 for c in chains))
    parts = [needs(ctx, fv, chains, level_pose(ctx, chains, level, local[f], trans[f], rows), cand, tol)
             for f in torch.split(frames, params.frame_chunk)]  # fmt: skip
    found = Needs(*(torch.cat([getattr(p, k) for p in parts], 1) for k in ("clear", "least", "cap")))
    half = ease_frames(params, motion.fps)
    ray, radius = choose(found, frames, 2 * half)
    full = local.new_zeros(local.shape[0], len(chains))
    full[frames] = radius
    cap = torch.full_like(full, math.inf)
    cap[frames] = found.cap.gather(0, ray[None])[0]
    nearest = (torch.arange(len(full))[:, None] - frames[None]).abs().argmin(1)  # eased frames take their run's ray
    return dilate_smooth(full, half).minimum(cap)[..., None] * cand.dirs[ray[nearest]]


def sinking(ctx: RefineContext, fv: FingerVertices, local: Tensor, trans: Tensor, num_chains: int, level: int = 0,
            chunk: int = 64) -> Tensor:  # fmt: skip
    """Deepest vertex ``(F, C)`` (m, the body's scale) of every chain from its ``level``-th joint on, on frames
    ``local (F, J, 4)``, ``trans (F, J, 3)``."""
    rows = torch.arange(len(fv.index))
    out = [local.new_zeros(0, num_chains)]
    for s in range(0, local.shape[0], chunk):
        grot, gpos = kinematics.forward_kinematics(
            ctx.target.skeleton.parents, local[s : s + chunk], trans[s : s + chunk]
        )
        out.append(chain_depths(depths(ctx, fv, rows, grot, gpos), fv, rows, num_chains, level))
    return torch.cat(out)


def sinking_on(ctx: RefineContext, fv: FingerVertices, motion: Motion, frames: Tensor, num_chains: int,
               level: int = 0) -> Tensor:  # fmt: skip
    """:func:`sinking` ``(F, C)`` measured on ``frames (n,)`` only (0 on the others)."""
    out = motion.rotations.new_zeros(motion.num_frames, num_chains)
    out[frames] = sinking(ctx, fv, motion.rotations[frames], motion.translations[frames], num_chains, level)
    return out


def clear_fingers(ctx: RefineContext, motion: Motion, params: FingerParams) -> tuple[Tensor, dict[str, Any]]:
    """The motion's local rotations ``(F, J, 4)`` with sinking fingers turned out of the body, and figures."""
    chains = finger_chains(motion.skeleton, ctx.target_mapping)
    local = motion.rotations.clone()
    if not chains or ctx.sdf is None:
        return local, {"frames_changed": 0, "fingers": len(chains)}
    fv = finger_vertices(ctx, chains)
    first = sinking(ctx, fv, local, motion.translations, len(chains))  # (F, C)
    before, to_cm = first.amax(1), 100.0 * REFERENCE_HEIGHT_M / ctx.target.height
    deep = before > params.tolerance_m * ctx.target.height / REFERENCE_HEIGHT_M
    report: dict[str, Any] = {"frames_changed": 0, "fingers": len(chains), "frames_sinking": int(deep.sum())}
    if not bool(deep.any()):
        return local, report
    # Later joints and the final check look only where a turn can reach: the sinking frames and their easing.
    near = torch.nonzero(dilate_smooth(deep[:, None].to(local.dtype), 2 * ease_frames(params, motion.fps))[:, 0] > 0)
    near = near.flatten()
    levels = max(len(c.joints) for c in chains)
    turns = local.new_zeros(local.shape[0], levels, len(chains), 2)
    for level in range(levels):
        now = replace(motion, rotations=local)
        depth = first if level == 0 else sinking_on(ctx, fv, now, near, len(chains), level)
        turns[:, level] = solve_level(ctx, fv, chains, level, now, params, depth)
        f = torch.nonzero((turns[:, level] != 0).flatten(1).any(1)).flatten()
        pose = level_pose(ctx, chains, level, local[f], motion.translations[f], f.new_zeros(0))
        local[f] = turned(pose.local, pose.grot, chains, level, pose.axes, torch.deg2rad(turns[f, level]))
    after = sinking_on(ctx, fv, replace(motion, rotations=local), near, len(chains)).amax(1)
    after = torch.where(torch.isin(torch.arange(len(after)), near), after, before)
    moved = (turns != 0).any(-1)  # (F, level, C)
    return local, {
        **report,
        "frames_changed": int(moved.flatten(1).any(1).sum()),
        "joints_turned": int(moved.sum()),
        "max_turn_deg": round(float(turns.norm(dim=-1).max()), 2),
        "finger_depth_before_cm": round(float(before.max()) * to_cm, 3),
        "finger_depth_after_cm": round(float(after.max()) * to_cm, 3),
    }


def run(ctx: RefineContext, motion: Motion, params: FingerParams | None = None) -> StageOutcome:
    """Turn sinking fingers onto the body's surface (module doc). Returns the motion and a report: frames changed,
    fingers, frames with a finger deeper than the tolerance, joint turns, the largest turn and the deepest finger
    vertex before and after (cm at 1.80 m, the stage's own SDF depth), seconds."""
    params = params or FingerParams()
    t0 = time.perf_counter()
    device = motion.rotations.device
    cpu = replace(motion, rotations=motion.rotations.cpu(), translations=motion.translations.cpu())
    with torch.no_grad():
        local, report = clear_fingers(ctx, cpu, params)
    report["seconds"] = round(time.perf_counter() - t0, 4)
    report["units"] = "lengths in cm at a 1.80 m character, angles in degrees"
    if report["frames_changed"] == 0:
        return StageOutcome(motion, report)
    return StageOutcome(replace(motion, rotations=local.to(device)), report)


__all__ = ["FingerChain", "FingerParams", "FingerVertices", "clear_fingers", "finger_chains", "finger_vertices", "run"]
