"""How deep each arm is in the body as the judge reads it (ACCEPTANCE.md: an arm vertex inside the torso, head,
other arm or a leg; a leg vertex inside the arm), on sampled vertices of the judge's closed parts
(:class:`retarget_core.contacts.hand_reach.ReachBody`): per frame figures for a never-worse check
(:func:`arm_penetration`) and for a stage that searches a turn of the arm out of the body. Lengths in metres on
the body's own scale.
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core.contacts.hand_reach import PosedParts
from retarget_core.geometry.triangle_bvh import PosedBoxes, closest_triangles, winding_numbers
from retarget_core.metrics.acceptance_body import HANDS, LIMB_TESTS

EMPTY = torch.zeros(0, dtype=torch.long)

Hits = list[tuple[Tensor, Tensor, Tensor, Tensor, bool]]  # per test: frame, point, depth (N,), areas (K,), on the arm


def arm_penetration(pp: PosedParts, side: int, max_depth: float) -> tuple[Tensor, Tensor, Tensor]:
    """Per frame of the chunk ``(n,)``, the judge's penetration that arm ``side`` takes part in: its tested vertices
    (its hand's too) inside a part the judge tests it against, and the legs' sampled vertices inside it. How many,
    the deepest, and their volume (each depth times its vertex's area; deeper than ``max_depth``: counted at it)."""
    return _figures(pp.posed.shape[0], _hits(pp, side, len(pp.rb.arm_points[side]), max_depth, with_legs=True))


def arm_search_figures(pp: PosedParts, side: int, max_depth: float) -> tuple[Tensor, Tensor]:
    """``(n,)`` twice, per frame of the chunk: the deepest of arm ``side``'s own sampled vertices, without its
    hand's (a swivel keeps the hand), inside a part the judge tests it against, and their volume. The legs'
    vertices inside the arm are not read: a leg in the arm is the arm in the leg, which is read, and the arm's
    tree need not be refit per turn."""
    _, deepest, volume = _figures(pp.posed.shape[0], _hits(pp, side, pp.rb.arm_cells[side], max_depth, False))
    return deepest, volume


def arm_penetration_and_search(pp: PosedParts, side: int,
                               max_depth: float) -> tuple[tuple[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]:  # fmt: skip
    """:func:`arm_penetration` and :func:`arm_search_figures` from one search: each point's depth does not
    depend on the points searched with it, so both are the same as two calls."""
    cells = pp.rb.arm_cells[side]
    hits = _hits(pp, side, len(pp.rb.arm_points[side]), max_depth, with_legs=True)
    arm_only: Hits = [(f[k < cells], k[k < cells], d[k < cells], area, on_arm) for f, k, d, area, on_arm in hits
                      if on_arm]  # fmt: skip
    n = pp.posed.shape[0]
    _, deepest, volume = _figures(n, arm_only)
    return _figures(n, hits), (deepest, volume)


def _hits(pp: PosedParts, side: int, arm_n: int, max_depth: float, with_legs: bool) -> Hits:
    """Per test of arm ``side`` (:func:`_tests`): the points inside, as :func:`_inside` gives them ``(f, k, d)``,
    their points' ``area (K,)``, and whether the points are the arm's (not a leg's)."""
    out = []
    for pts, area, name, on_arm in _tests(pp, side, arm_n, with_legs):
        out.append((*_inside(pp, torch.from_numpy(pts), name, max_depth), area, on_arm))
    return out


def _figures(n: int, hits: Hits) -> tuple[Tensor, Tensor, Tensor]:
    """``(n,)`` how many points of ``hits`` (:func:`_hits`) are inside, the deepest and their volume."""
    count, deepest, total = torch.zeros(n), torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    for f, k, d, area, _ in hits:
        if len(f):
            count.index_add_(0, f, torch.ones(len(f)))
            total.index_add_(0, f, d * area[k])
            deepest = deepest.scatter_reduce(0, f, d, "amax")
    return count, deepest, total


def _tests(pp: PosedParts, side: int, arm_n: int, with_legs: bool) -> list[tuple]:
    """What arm ``side``'s penetration is read on: ``(points, areas, part, on_arm)``: the first ``arm_n`` of its
    sampled points against each part the judge tests the arm against, and (``with_legs``) each leg's points
    against the arm."""
    arm = f"{HANDS[side]}_arm"
    pts, area = pp.rb.arm_points[side][:arm_n], pp.rb.arm_area[side][:arm_n]
    tests = [(pts, area, name, True) for name in LIMB_TESTS[arm]]
    legs = [(p, a, arm, False) for p, a in zip(pp.rb.leg_points, pp.rb.leg_area, strict=True)] if with_legs else []
    return tests + legs


def _inside(pp: PosedParts, pts: Tensor, name: str, max_depth: float) -> tuple[Tensor, Tensor, Tensor]:
    """The vertices ``pts (K,)`` inside part ``name`` on the chunk's frames: frame and index into ``pts`` ``(N,)``
    and depth ``(N,)`` (at most ``max_depth``)."""
    f, k, d, _, _ = points_inside(pp, pts, name, max_depth)
    return f, k, torch.nan_to_num(d, posinf=max_depth).clamp_max(max_depth)


def points_inside(pp: PosedParts, pts: Tensor, name: str,
                  max_depth: float) -> tuple[Tensor, Tensor, Tensor, Tensor, PosedBoxes | None]:  # fmt: skip
    """The vertices ``pts (K,)`` inside part ``name`` on the chunk's frames: frame and index into ``pts`` ``(N,)``,
    depth ``(N,)`` and nearest triangle of the part's closed mesh ``(N,)`` (``inf`` and -1 deeper than
    ``max_depth``), and the part's tree boxes they were read on (None when no point is in the part's box)."""
    empty = (EMPTY, EMPTY, torch.zeros(0, dtype=torch.float64), EMPTY, None)
    closed = pp.rb.body.part(name)
    if closed is None or len(pts) == 0:
        return empty
    at = pp.posed[:, pts]  # (n, K, 3)
    lo, hi = pp.box(name)
    f, k = torch.nonzero(((at >= lo) & (at <= hi)).all(dim=-1), as_tuple=True)
    if len(f) == 0:
        return empty
    tree, boxes = pp.rb.trees[name], pp.tree_boxes(name, torch.unique(f))
    inside = winding_numbers(tree, boxes, f, at[f, k]).abs() > 0.5
    f, k = f[inside], k[inside]
    d, face = closest_triangles(tree, boxes, f, at[f, k], max_depth)
    return f, k, d, face, boxes


__all__ = ["arm_penetration", "arm_penetration_and_search", "arm_search_figures", "points_inside"]
