"""Finger clearance: fingers resting on the body are turned onto its surface, not into it.

The copy sets every finger joint from the source (docs/mapping.md) and the other refinement stages turn only the
22 canonical joints, so a hand that the contact stages put on a thicker thigh keeps the copy's finger angles, and
its fingers (most often the thumb, whose base is part of the palm) can end inside the thigh. This stage runs last
and turns finger joints only, and only where a finger is inside another part of the body deeper than its palm:

1. Find: every finger vertex's depth, and its hand's palm's, inside the parts a hand is tested against, on every
   frame (:mod:`retarget_core.refine.finger_depth`: the collision stages' depth). A finger *sinks* where it is
   deeper than its palm by more than ``tolerance_m``; it is turned only on the sinking frames of a contact (a run
   of frames with the finger in the body) in which it goes deeper than its palm by more than ``allowance_m``
   somewhere, so a finger that comes near its palm's depth for a while and sinks again is turned both times. A
   palm in the body (the skinning fold at the hip on a walk, a hand pressed on a thigh) is the stages' before,
   which no finger turn can mend, and a finger brushing a surface a few millimetres deep is left alone: no finger
   flicks on a walk. Everywhere else the fingers keep the copy's rotations bit for bit.
2. Turn, proximal to distal (first, middle, last joint of each finger and of the thumb): on the frames where a
   finger sinks from that joint on, candidate turns of the joint are measured on rays from no turn (flexion and
   extension for a hinge, ``directions`` rays in the flexion-spread plane for the thumb's first joint), every
   ``COARSE`` x ``step_deg`` up to ``max_turn_deg``; a ray "clears" a frame at the smallest turn along it that
   takes the finger to its goal: its palm's depth, or the least depth any candidate inside the joint's range
   reaches, plus ``tolerance_m``. Per finger and run of such frames one ray is kept (the one whose worst frame
   needs the least turn), so the finger does not flip between solutions from frame to frame; the turn along it
   is refined to ``step_deg`` and eased in and out over ``ease_seconds`` each side (a running maximum, then a
   binomial average: never less than a frame needs, never beyond the joint's range on the frames measured). The
   segments beyond follow (their local rotations are kept), so a knuckle that lifts the whole finger leaves
   nothing for the next joint. Palm, wrist and body do not move: the palm's contact is what the contact stages
   made it.

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
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.canonical import FINGERS, JointMapping
from retarget_core.context import RefineContext, StageOutcome
from retarget_core.energy.sdf import segment_matrices
from retarget_core.motion import Motion
from retarget_core.refine.finger_depth import (
    FingerVertices,
    chain_depths,
    finger_depths,
    finger_vertices,
    palms,
    sinking,
)
from retarget_core.skeleton import Skeleton

REFERENCE_HEIGHT_M = 1.80
SIDES: tuple[str, ...] = ("Left", "Right")
SEGMENTS: tuple[int, ...] = (1, 2, 3)  # the joints turned, proximal first (a metacarpal, 0, stays with the palm)
FINGER_RANGE_DEG: tuple[tuple[float, float], ...] = ((-30.0, 90.0), (-5.0, 100.0), (-10.0, 80.0))
THUMB_RANGE_DEG: tuple[tuple[float, float], ...] = ((-20.0, 45.0), (-10.0, 60.0), (-20.0, 80.0))
THUMB_SPREAD_DEG = 40.0  # the thumb's CMC spread either way from the copy; every other joint is a hinge here
MIN_AXIS = 0.3  # a thumb bone this close to the palm normal (|bone x n|) flexes about the hand's axis instead
COARSE = 3  # rays are searched every COARSE steps, then the turn kept along one is refined to a step
POSES_PER_BATCH = 2048  # candidate poses measured at once (memory: poses x finger vertices of sinking fingers)


@dataclass(frozen=True)
class FingerParams:
    """Settings (lengths at a 1.80 m character)."""

    # Depth a finger may keep beyond its palm's: below it a finger is on the surface (about the SDF grids' error).
    tolerance_m: float = 0.001
    # A finger is turned only in a contact (a run of frames with it in the body) where it goes deeper than its
    # palm by more than this somewhere: a finger brushing a surface is left alone.
    allowance_m: float = 0.005
    # Candidate turns: every step_deg up to max_turn_deg along each ray; rays around a joint that also spreads.
    max_turn_deg: float = 45.0
    step_deg: float = 2.5
    directions: int = 12
    # Turns are eased in and out over this long each side of the frames that need them (and never drop between).
    ease_seconds: float = 0.2


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


def turned(local: Tensor, grot: Tensor, chains: list[FingerChain], level: int, axes: tuple[Tensor, Tensor],
           angle: Tensor) -> Tensor:  # fmt: skip
    """``local (F, J, 4)`` with each chain's ``level``-th joint turned in the world by ``angle (F, C, 2)`` (radians:
    flexion, spread) about ``axes`` (flexion and spread axes, ``(F, C, 3)`` each); ``grot (F, J, 4)`` the world
    rotations of ``local``. Untouched where both angles are 0."""
    out = local.clone()
    for c, chain in enumerate(chains):
        if level >= len(chain.joints) or not bool((angle[:, c] != 0).any()):
            continue
        j = chain.joints[level]
        back = rot.inv(grot[:, j])  # world axes into the joint's own frame: G' = R_flex R_spread G
        flex = rot.axis_angle(rot.apply(back, axes[0][:, c]), angle[:, c, 0])
        spread = rot.axis_angle(rot.apply(back, axes[1][:, c]), angle[:, c, 1])
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


@dataclass(frozen=True)
class Level:
    """One level of the search: the joints at place ``level`` of every chain, on ``motion``'s frames."""

    ctx: RefineContext
    fv: FingerVertices
    chains: list[FingerChain]
    level: int
    motion: Motion

    def pose(self, frames: Tensor, rows: Tensor) -> LevelPose:
        """The :class:`LevelPose` of ``frames (n,)``, measuring the finger vertex rows ``rows (R,)``."""
        local, trans = self.motion.rotations[frames], self.motion.translations[frames]
        grot, gpos = kinematics.forward_kinematics(self.ctx.target.skeleton.parents, local, trans)
        axes = chain_axes(self.chains, self.level, grot, gpos)
        return LevelPose(self.level, local, trans, grot, gpos, axes, bends(self.chains, self.level, grot, gpos, axes[0]),
                         rows)  # fmt: skip

    def chunks(self, frames: Tensor, want: Tensor, size: int) -> Iterator[tuple[Tensor, LevelPose]]:
        """``size`` frames of ``frames (n,)`` at a time: their places in ``frames`` and their pose, measuring the
        vertices of the chains that ``want (n, C)`` there."""
        for idx in torch.split(torch.arange(len(frames)), size):
            rows = torch.nonzero(want[idx].any(0).index_select(0, self.fv.chain)).flatten()
            yield idx, self.pose(frames[idx], rows)


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
    spreads; along each, every ``COARSE`` steps up to ``max_turn_deg``."""
    n = params.directions if spread else 2
    psi = 2.0 * math.pi * torch.arange(n, dtype=torch.float64) / n
    dirs = torch.stack([psi.cos(), psi.sin()], -1)
    dirs = torch.where(dirs.abs() < 1e-9, 0.0, dirs).float()  # exact zeros: a hinge's rays never spread
    step = COARSE * params.step_deg
    radii = step * torch.arange(math.ceil(params.max_turn_deg / step - 1e-6) + 1, dtype=torch.float32)
    return Candidates(dirs, radii.clamp_max(params.max_turn_deg))


def measure_turns(job: Level, pose: LevelPose, turns: Tensor, want: Tensor) -> tuple[Tensor, Tensor]:
    """Depth ``(M, n, C)`` of every chain's finger from ``pose.level`` on, and of the palm vertices it drags, with
    that joint turned by ``turns (M, n, C, 2)`` (degrees), where ``want (M, n, C)`` (elsewhere 0, not turned)."""
    (m, n, c_n), rep = turns.shape[:3], (turns.shape[0], 1, 1)
    moving = want.flatten(0, 1).any(0).tolist()
    turns = torch.where(want[..., None], turns, 0.0)
    axes = (pose.axes[0].repeat(rep), pose.axes[1].repeat(rep))
    local = turned(pose.local.repeat(rep), pose.grot.repeat(rep), job.chains, pose.level, axes,
                   torch.deg2rad(turns).reshape(-1, c_n, 2))  # fmt: skip
    roots = [c.joints[pose.level] for c, on in zip(job.chains, moving, strict=True)
             if on and pose.level < len(c.joints)]  # fmt: skip
    grot, gpos = subtree_fk(job.ctx.target.skeleton, roots, local, pose.trans.repeat(rep), pose.grot.repeat(rep),
                            pose.gpos.repeat(rep))  # fmt: skip
    mats = segment_matrices(job.ctx.target, job.ctx.parts, pose.grot, pose.gpos).repeat(m, 1, 1, 1)  # none moves
    every = finger_depths(job.ctx, job.fv, pose.rows, grot, gpos, mats, want.flatten(0, 1))
    depth, dragged = (chain_depths(every, job.fv, pose.rows, c_n, pose.level, own).view(m, n, c_n)
                      for own in (True, False))  # fmt: skip
    return depth, dragged


@dataclass
class Needs:
    """Per ray, frame and chain ``(D, n, C)`` (degrees): ``clear`` the smallest turn along the ray that takes the
    finger to its ``goal`` (inf: none does), ``least`` the turn of least depth along it, ``cap`` the largest turn
    up to which every turn along it is feasible: inside the joint's range, dragging no palm vertex deeper than
    ``drag``. Per frame and chain ``(n, C)`` (m): ``goal`` the depth a finger may keep: its palm's, or the least
    any feasible candidate reaches, plus the tolerance; ``drag`` the dragged palm vertices' depth with no turn
    plus the tolerance."""

    clear: Tensor
    least: Tensor
    cap: Tensor
    goal: Tensor
    drag: Tensor

    @staticmethod
    def cat(parts: list[Needs]) -> Needs:
        """Parts over consecutive frames joined."""
        return Needs(
            *(torch.cat([getattr(p, k) for p in parts], -2) for k in ("clear", "least", "cap", "goal", "drag"))
        )


def needs(job: Level, pose: LevelPose, palm: Tensor, sinks: Tensor, cand: Candidates, tol: float) -> Needs:
    """Every candidate turn of every chain's ``pose.level``-th joint on ``pose``'s frames where it ``sinks (n,
    C)``, measured (``palm (n, C)``: the depth of each chain's palm, m; ``tol``: m). Elsewhere no turn is needed."""
    (n, c_n), (d_n, r_n) = pose.bend.shape, (len(cand.dirs), len(cand.radii))
    turns = cand.turns.to(pose.local.dtype)[:, None, None, :].expand(-1, n, c_n, 2)  # (M, n, C, 2)
    fit = feasible(job.chains, pose.level, pose.bend, turns).view(d_n, r_n, n, c_n).cumprod(1).bool()
    want = (fit & sinks).view(-1, n, c_n)  # along a ray up to its first turn out of range
    depth, dragged = (x.view(d_n, r_n, n, c_n) for x in measure_turns(job, pose, turns, want))
    drag = dragged[0, 0] + tol
    ok = (fit & (dragged <= drag)).cumprod(1).bool()  # along a ray, up to its first infeasible turn
    goal = torch.maximum(depth.masked_fill(~ok, math.inf).amin((0, 1)), palm) + tol
    radius = cand.radii.to(depth.dtype)[None, :, None, None].expand_as(depth)
    clear = radius.masked_fill(~(ok & (depth <= goal)), math.inf).amin(1)
    least = cand.radii.to(depth.dtype)[depth.masked_fill(~ok, math.inf).argmin(1)]
    return Needs(clear, least, radius.masked_fill(~ok, -math.inf).amax(1), goal, drag)


def choose(found: Needs, frames: Tensor, gap: int) -> tuple[Tensor, Tensor, Tensor]:
    """One ray per chain and run of frames (``frames (n,)`` split where more than ``gap`` apart): the one whose
    worst frame needs the least turn (a ray clearing every frame first). Returns the ray ``(n, C)``, the turn
    along it ``(n, C)`` (degrees: the clearing one, else the least deep) and whether it clears ``(n, C)``."""
    ray = torch.zeros(found.clear.shape[1:], dtype=torch.long)
    cut = torch.nonzero(frames.diff() > gap).flatten() + 1
    for run in torch.tensor_split(torch.arange(len(frames)), cut.tolist()):
        need = found.clear[:, run]  # (D, r, C)
        misses = torch.isinf(need).sum(1)
        worst = need.masked_fill(torch.isinf(need), 0.0).amax(1)
        ray[run] = (misses * 1e4 + worst).argmin(0)[None]
    pick = ray[None]
    clear, least = found.clear.gather(0, pick)[0], found.least.gather(0, pick)[0]
    clears = torch.isfinite(clear)
    return ray, torch.where(clears, clear, least), clears


def finer(job: Level, pose: LevelPose, dirs: Tensor, radius: Tensor, redo: Tensor, found: Needs,
          step: float) -> Tensor:  # fmt: skip
    """``radius (n, C)`` (degrees, a clearing turn along ``dirs (n, C, 2)`` found every ``COARSE`` steps) made,
    where ``redo (n, C)``, the smallest of it and the turns one step, two steps, .. short of it that take the
    finger to ``found.goal`` and drag no palm vertex beyond ``found.drag`` (``found``: ``(n, C)`` fields of these
    frames)."""
    shorter = radius[None] - step * torch.arange(COARSE - 1, 0, -1, dtype=radius.dtype)[:, None, None]  # (K, n, C)
    want = (shorter > 0) & redo
    depth, dragged = measure_turns(job, pose, dirs[None] * shorter.clamp_min(0.0)[..., None], want)
    good = (depth <= found.goal) & (dragged <= found.drag) & want
    return shorter.masked_fill(~good, math.inf).amin(0).minimum(radius)


def refined(job: Level, frames: Tensor, dirs: Tensor, radius: Tensor, redo: Tensor, found: Needs,
            step: float) -> Tensor:  # fmt: skip
    """``radius (n, C)`` on ``frames (n,)`` with :func:`finer` turns where ``redo (n, C)``."""
    at = torch.nonzero(redo.any(1)).flatten()
    out = radius.clone()
    for idx, pose in job.chunks(frames[at], redo[at], max(1, POSES_PER_BATCH // (COARSE - 1))):
        k = at[idx]
        sub = Needs(*(getattr(found, f)[..., k, :] for f in ("clear", "least", "cap", "goal", "drag")))
        out[k] = finer(job, pose, dirs[k], radius[k], redo[k], sub, step)
    return out


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


def buried(depth: Tensor, palm: Tensor, tol: float, allowance: float) -> Tensor:
    """``(F, C)``: the frames where a finger is deeper than its palm by more than ``tol`` in each of its contacts
    (runs of frames with ``depth (F, C)`` above ``tol``, m) in which it goes deeper than its palm (``palm (F, C)``)
    by more than ``allowance`` somewhere. A contact is the whole time a finger is in the body, so a finger that
    comes near its palm's depth for a while is still turned on the frames of that contact where it sinks again."""
    inside, excess = depth > tol, depth - palm
    start = inside & ~torch.cat([torch.zeros_like(inside[:1]), inside[:-1]])
    run = start.long().cumsum(0)  # each chain's contacts numbered from 1 (0: before its first)
    peak = torch.zeros(depth.shape[0] + 1, depth.shape[1], dtype=depth.dtype)
    peak = peak.scatter_reduce(0, run, excess.masked_fill(~inside, 0.0), "amax")
    return inside & (excess > tol) & (peak.gather(0, run) > allowance)


def solve_level(job: Level, params: FingerParams, deep: Tensor, palm: Tensor) -> Tensor:
    """Turns ``(F, C, 2)`` (degrees: flexion, spread) of every chain's ``job.level``-th joint over the clip (module
    doc): measured on the frames where a finger sinks beyond its palm from that joint on (``deep (F, C)``; ``palm
    (F, C)`` its palm's depth, m), one ray per run of them, eased in and out. Joints that also spread (the thumb's
    first) and hinges are searched apart, each on its own rays."""
    spreads = torch.tensor([job.level < len(c.joints) and float(c.spread[job.level]) > 0 for c in job.chains])
    turns = job.motion.rotations.new_zeros(deep.shape[0], len(job.chains), 2)
    for members, spread in ((spreads, True), (~spreads, False)):
        if bool((deep & members).any()):
            turns += solve_rays(job, params, deep & members, palm, candidates(params, spread))
    return turns


def solve_rays(job: Level, params: FingerParams, deep: Tensor, palm: Tensor, cand: Candidates) -> Tensor:
    """:func:`solve_level`'s turns ``(F, C, 2)`` of the chains that sink somewhere in ``deep (F, C)``, on the rays
    ``cand`` (0 for the others)."""
    tol = params.tolerance_m * job.ctx.target.height / REFERENCE_HEIGHT_M
    frames = torch.nonzero(deep.any(1)).flatten()
    size = max(1, POSES_PER_BATCH // len(cand.turns))
    sinks = deep[frames]
    found = Needs.cat([needs(job, pose, palm[frames[idx]], sinks[idx], cand, tol)
                       for idx, pose in job.chunks(frames, sinks, size)])  # fmt: skip
    half = ease_frames(params, job.motion.fps)
    ray, radius, clears = choose(found, frames, 2 * half)
    radius = refined(job, frames, cand.dirs[ray], radius, clears & (radius > 0), found, params.step_deg)
    full = palm.new_zeros(deep.shape)
    full[frames] = radius
    cap = torch.full_like(full, math.inf)
    cap[frames] = found.cap.gather(0, ray[None])[0]
    nearest = (torch.arange(len(full))[:, None] - frames[None]).abs().argmin(1)  # eased frames take their run's ray
    return dilate_smooth(full, half).minimum(cap)[..., None] * cand.dirs[ray[nearest]]


def sinking_on(ctx: RefineContext, fv: FingerVertices, motion: Motion, reach: Tensor, level: int = 0) -> Tensor:
    """:func:`sinking` ``(F, C)`` measured where ``reach (F, C)`` only: its frames and chains (0 on the others)."""
    out = motion.rotations.new_zeros(reach.shape)
    frames = torch.nonzero(reach.any(1)).flatten()
    out[frames] = sinking(ctx, fv, motion.rotations[frames], motion.translations[frames], reach.shape[1], level,
                          reach.any(0))  # fmt: skip
    return out


def turn_levels(ctx: RefineContext, fv: FingerVertices, chains: list[FingerChain], motion: Motion,
                params: FingerParams, chosen: Tensor, palm: Tensor, reach: Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
    """The motion's local rotations ``(F, J, 4)`` with every level turned, proximal first, and the turns ``(F,
    levels, C, 2)`` (degrees); ``chosen (F, C)`` where the fingers are turned (:func:`buried`), ``palm (F, C)``
    their palms' depth, ``reach (F, C)`` where their turns reach: later joints turn there, where the finger from
    that joint on is still deeper than its palm by more than the tolerance."""
    local = motion.rotations.clone()
    levels = max(len(c.joints) for c in chains)
    turns = local.new_zeros(local.shape[0], levels, len(chains), 2)
    tol = params.tolerance_m * ctx.target.height / REFERENCE_HEIGHT_M
    for level in range(levels):
        job = Level(ctx, fv, chains, level, replace(motion, rotations=local))
        deep = chosen if level == 0 else reach & (sinking_on(ctx, fv, job.motion, reach, level) > palm + tol)
        turns[:, level] = solve_level(job, params, deep, palm)
        f = torch.nonzero((turns[:, level] != 0).flatten(1).any(1)).flatten()
        pose = job.pose(f, f.new_zeros(0))
        local[f] = turned(pose.local, pose.grot, chains, level, pose.axes, torch.deg2rad(turns[f, level]))
    return local, turns


def clear_fingers(ctx: RefineContext, motion: Motion, params: FingerParams) -> tuple[Tensor, dict[str, Any]]:
    """The motion's local rotations ``(F, J, 4)`` with fingers that sink beyond their palm turned out of the body,
    and figures."""
    chains = finger_chains(motion.skeleton, ctx.target_mapping)
    if not chains or ctx.sdf is None:
        return motion.rotations.clone(), {"frames_changed": 0, "fingers": len(chains)}
    fv, tol = finger_vertices(ctx, chains), params.tolerance_m * ctx.target.height / REFERENCE_HEIGHT_M
    first = sinking(ctx, fv, motion.rotations, motion.translations, len(chains))  # (F, C)
    inside = torch.nonzero(first.amax(1) > tol).flatten()  # only there can a finger sink beyond its palm
    palm = torch.zeros_like(first)
    if len(inside):
        palm[inside] = palms(ctx, fv, motion.rotations[inside], motion.translations[inside])
    chosen = buried(first, palm, tol, params.allowance_m * ctx.target.height / REFERENCE_HEIGHT_M)
    to_cm = 100.0 * REFERENCE_HEIGHT_M / ctx.target.height
    report: dict[str, Any] = {"frames_changed": 0, "fingers": len(chains), "frames_in_body": len(inside),
                              "frames_beyond_palm": int((first - palm > tol).any(1).sum()),
                              "frames_sinking": int(chosen.any(1).sum()),
                              "finger_depth_before_cm": round(float(first.max()) * to_cm, 3),
                              "beyond_palm_before_cm": round(float((first - palm).clamp_min(0.0).max()) * to_cm, 3)}  # fmt: skip
    if not bool(chosen.any()):
        return motion.rotations.clone(), report
    # Later joints and the final check look only where a turn can reach: the chosen frames and their easing.
    reach = dilate_smooth(chosen.to(first.dtype), 2 * ease_frames(params, motion.fps)) > 0
    local, turns = turn_levels(ctx, fv, chains, motion, params, chosen, palm, reach)
    after = torch.where(reach, sinking_on(ctx, fv, replace(motion, rotations=local), reach), first)
    moved = (turns != 0).any(-1)  # (F, level, C)
    return local, {
        **report,
        "frames_changed": int(moved.flatten(1).any(1).sum()),
        "joints_turned": int(moved.sum()),
        "max_turn_deg": round(float(turns.norm(dim=-1).max()), 2),
        "finger_depth_after_cm": round(float(after.max()) * to_cm, 3),
        "beyond_palm_after_cm": round(float((after - palm).clamp_min(0.0).max()) * to_cm, 3),
    }


def run(ctx: RefineContext, motion: Motion, params: FingerParams | None = None) -> StageOutcome:
    """Turn fingers that sink beyond their palm onto the body's surface (module doc). Returns the motion and a
    report: frames changed, fingers, frames with a finger in the body and with one deeper than its palm by more
    than the tolerance, joint turns, the largest turn, the deepest finger vertex and the most a finger is deeper
    than its palm, before and after (cm at 1.80 m, the stage's own SDF depth), seconds."""
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


__all__ = ["FingerChain", "FingerParams", "clear_fingers", "finger_chains", "run"]
