"""How deep each arm is in the body as the judge reads it (ACCEPTANCE.md: an arm vertex inside the torso, head,
other arm or a leg; a leg vertex inside the arm), on sampled vertices of the judge's closed parts
(:class:`retarget_core.contacts.hand_reach.ReachBody`): per frame figures for a never-worse check
(:func:`arm_penetration`), and the pairs of vertex and nearest surface point that make them, with the vertices
that are near a part without being in it (:func:`arm_pairs`), for a stage that turns the arm out.
Lengths in metres on the body's own scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.contacts.hand_reach import PosedParts
from retarget_core.geometry.closest_point import closest_points
from retarget_core.geometry.triangle_bvh import closest_triangles, winding_numbers
from retarget_core.metrics.acceptance_body import HANDS, LIMB_TESTS

EMPTY = torch.zeros(0, dtype=torch.long)


def arm_penetration(pp: PosedParts, side: int, max_depth: float) -> tuple[Tensor, Tensor, Tensor]:
    """Per frame of the chunk ``(n,)``, the judge's penetration that arm ``side`` takes part in: its tested vertices
    inside a part the judge tests it against, and the legs' sampled vertices inside it. How many, the deepest,
    and their volume (each depth times its vertex's area; deeper than ``max_depth``: counted at it)."""
    n = pp.posed.shape[0]
    count, deepest, total = torch.zeros(n), torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    for pts, area, name, _ in _tests(pp, side, len(pp.rb.arm_points[side])):
        f, k, d = _inside(pp, torch.from_numpy(pts), name, max_depth)
        if len(f):
            count.index_add_(0, f, torch.ones(len(f)))
            total.index_add_(0, f, d * area[k])
            deepest = deepest.scatter_reduce(0, f, d, "amax")
    return count, deepest, total


def _tests(pp: PosedParts, side: int, arm_n: int) -> list[tuple]:
    """What arm ``side``'s penetration is read on: ``(points, areas, part, arm_moves)``: the first ``arm_n`` of
    its sampled points against each part the judge tests the arm against (the points move with the arm), and
    each leg's points against the arm (the part moves)."""
    arm = f"{HANDS[side]}_arm"
    pts, area = pp.rb.arm_points[side][:arm_n], pp.rb.arm_area[side][:arm_n]
    tests = [(pts, area, name, True) for name in LIMB_TESTS[arm]]
    return tests + [(p, a, arm, False) for p, a in zip(pp.rb.leg_points, pp.rb.leg_area, strict=True)]


def _inside(pp: PosedParts, pts: Tensor, name: str, max_depth: float) -> tuple[Tensor, Tensor, Tensor]:
    """The vertices ``pts (K,)`` inside part ``name`` on the chunk's frames: frame and index into ``pts`` ``(N,)``
    and depth ``(N,)`` (at most ``max_depth``)."""
    closed = pp.rb.body.part(name)
    if closed is None or len(pts) == 0:
        return EMPTY, EMPTY, torch.zeros(0, dtype=torch.float64)
    at = pp.posed[:, pts]  # (n, K, 3)
    f, k = _in_box(pp, at, closed.vertices, 0.0)
    got = pp.get(name) if len(f) else None
    if got is None:
        return EMPTY, EMPTY, torch.zeros(0, dtype=torch.float64)
    tree, boxes = pp.rb.trees[name], got[1]
    inside = winding_numbers(tree, boxes, f, at[f, k]).abs() > 0.5
    f, k = f[inside], k[inside]
    d, _ = closest_triangles(tree, boxes, f, at[f, k], max_depth)
    return f, k, torch.nan_to_num(d, posinf=max_depth).clamp_max(max_depth)


def _in_box(pp: PosedParts, at: Tensor, part_vertices, margin: float) -> tuple[Tensor, Tensor]:
    """``(frame, index)`` of the points ``at (n, K, 3)`` within ``margin`` of the part's posed box (its tree's
    root box: the caps lie within it)."""
    own = pp.posed[:, torch.from_numpy(part_vertices)]
    lo, hi = own.amin(dim=1)[:, None] - margin, own.amax(dim=1)[:, None] + margin
    return torch.nonzero(((at >= lo) & (at <= hi)).all(dim=-1), as_tuple=True)


@dataclass
class ArmPairs:
    """Per pair ``(N,)`` of a sampled vertex in or near a part and the part's nearest surface point: ``frame`` (in
    the chunk), ``point`` and ``surface`` ``(N, 3)``, ``depth`` (signed: > 0 inside, < 0 outside), ``into (N, 3)``
    the unit direction that goes deeper, ``arm_moves`` (the vertex is the arm's; else the surface is) and
    ``index`` into the arm's sampled points (-1 for a leg's)."""

    frame: Tensor
    point: Tensor
    surface: Tensor
    depth: Tensor
    into: Tensor
    arm_moves: Tensor
    index: Tensor

    @staticmethod
    def cat(pairs: list[ArmPairs]) -> ArmPairs:
        return ArmPairs(*(torch.cat([getattr(p, f) for p in pairs]) for f in ArmPairs.__dataclass_fields__))


def arm_pairs(pp: PosedParts, side: int, near: float, max_depth: float) -> ArmPairs:
    """The pairs (:class:`ArmPairs`) of arm ``side`` on the chunk's frames: its sampled arm vertices (not its
    hand's) in or within ``near`` of the parts the judge tests them against, and the legs' sampled vertices in
    or near the arm; depths searched up to ``max_depth``."""
    out = []
    for pts, _, name, arm_moves in _tests(pp, side, pp.rb.arm_cells[side]):
        got = _part_pairs(pp, torch.from_numpy(pts), name, near, max_depth)
        if got is not None:
            f, k, p, s, d = got
            inside = (d > 0)[:, None]
            gap = (p - s) / (p - s).norm(dim=-1, keepdim=True).clamp_min(1e-12)
            into = torch.where(inside, gap, -gap)
            index = k if arm_moves else torch.full_like(k, -1)
            out.append(ArmPairs(f, p, s, d, into, torch.full_like(k, arm_moves, dtype=torch.bool), index))
    if not out:
        z3 = torch.zeros(0, 3, dtype=torch.float64)
        return ArmPairs(EMPTY, z3, z3, torch.zeros(0, dtype=torch.float64), z3, torch.zeros(0, dtype=torch.bool), EMPTY)
    return ArmPairs.cat(out)


def _part_pairs(pp: PosedParts, pts: Tensor, name: str, near: float,
                max_depth: float) -> tuple[Tensor, ...] | None:  # fmt: skip
    """Points ``pts (K,)`` inside part ``name`` (up to ``max_depth`` deep) or outside within ``near``: frame,
    index into ``pts``, point, nearest surface point and signed depth, each ``(N, ...)``."""
    closed = pp.rb.body.part(name)
    if closed is None or len(pts) == 0:
        return None
    at = pp.posed[:, pts]
    f, k = _in_box(pp, at, closed.vertices, near)
    got = pp.get(name) if len(f) else None
    if got is None:
        return None
    tree, boxes = pp.rb.trees[name], got[1]
    p = at[f, k]
    d, face = closest_triangles(tree, boxes, f, p, max_depth)
    found = torch.isfinite(d)
    f, k, p, d, face = f[found], k[found], p[found], d[found], face[found]
    inside = winding_numbers(tree, boxes, f, p).abs() > 0.5
    keep = inside | (d <= near)
    f, k, p, d, face, inside = f[keep], k[keep], p[keep], d[keep], face[keep], inside[keep]
    local = got[0]
    tri = tree.faces[face]
    s = closest_points(p, *(local[f, tri[:, c]] for c in range(3)))
    return f, k, p, s, torch.where(inside, d, -d)


__all__ = ["ArmPairs", "arm_pairs", "arm_penetration"]
