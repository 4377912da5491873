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
from retarget_core.geometry.bvh_kernels import rows_in_boxes
from retarget_core.geometry.triangle_bvh import PosedBoxes, closest_triangles, winding_numbers
from retarget_core.metrics.acceptance_body import HANDS, LIMB_TESTS

EMPTY = torch.zeros(0, dtype=torch.long)

Hits = list[tuple[Tensor, Tensor, Tensor, Tensor, bool]]  # per test: frame, point, depth (N,), areas (K,), on the arm


def arm_penetration(pp: PosedParts, side: int, max_depth: float) -> tuple[Tensor, Tensor, Tensor]:
    """Per frame of the chunk ``(n,)``, the judge's penetration that arm ``side`` takes part in: its tested vertices
    (its hand's too) inside a part the judge tests it against, and the legs' sampled vertices inside it. How many,
    the deepest, and their volume (each depth times its vertex's area; deeper than ``max_depth``: counted at it)."""
    return _figures(pp.posed.shape[0], _hits(pp, side, len(pp.rb.arm_points[side]), max_depth, with_legs=True))


def arm_search_figures(pp: PosedParts, side: int, max_depth: float, legs_on: Tensor) -> tuple[Tensor, Tensor]:
    """``(n,)`` twice, per frame of the chunk: the deepest of arm ``side``'s own sampled vertices, without its
    hand's (a swivel keeps the hand), inside a part the judge tests it against, and of the legs' sampled vertices
    inside the arm on the frames ``legs_on (n,)`` (bool) only; and their volume. Reading the legs in the arm means
    refitting the arm's tree for every way it is moved: a stage reads them where they were in it before it moved
    the arm (on a blocky, low-poly body a leg's corner in the arm is not the arm in the leg), and leaves the rest
    to its never-worse check, which reads them everywhere."""
    n = pp.posed.shape[0]
    hits = _hits(pp, side, pp.rb.arm_cells[side], max_depth, with_legs=False)
    rows = torch.nonzero(legs_on).flatten()
    if len(rows):
        some = pp.frames(rows)
        hits += [(rows[f], k, d, area, on_arm) for f, k, d, area, on_arm in _leg_hits(some, side, max_depth)]
    _, deepest, volume = _figures(n, hits)
    return deepest, volume


def arm_penetration_and_search(pp: PosedParts, side: int,
                               max_depth: float) -> tuple[tuple[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:  # fmt: skip
    """:func:`arm_penetration`, and :func:`arm_search_figures` with the legs read on every frame and ``(n,)``
    whether a leg's point is in the arm, from one search: each point's depth does not depend on the points
    searched with it, so both are the same as separate calls."""
    cells = pp.rb.arm_cells[side]
    hits = _hits(pp, side, len(pp.rb.arm_points[side]), max_depth, with_legs=True)
    search: Hits = [(f[k < cells], k[k < cells], d[k < cells], area, on_arm) if on_arm else (f, k, d, area, on_arm)
                    for f, k, d, area, on_arm in hits]  # fmt: skip
    n = pp.posed.shape[0]
    legs_in = torch.zeros(n, dtype=torch.bool)
    for f, _, _, _, on_arm in hits:
        if not on_arm:
            legs_in[f] = True
    _, deepest, volume = _figures(n, search)
    return _figures(n, hits), (deepest, volume, legs_in)


def _hits(pp: PosedParts, side: int, arm_n: int, max_depth: float, with_legs: bool) -> Hits:
    """What arm ``side``'s penetration is read on, per test: the first ``arm_n`` of its sampled points inside each
    part the judge tests the arm against, and (``with_legs``) each leg's points inside the arm; the points inside,
    as :func:`_inside` gives them ``(f, k, d)``, their points' ``area (K,)``, and whether they are the arm's."""
    pts, area = torch.from_numpy(pp.rb.arm_points[side][:arm_n]), pp.rb.arm_area[side][:arm_n]
    out: Hits = [(*_inside(pp, pts, name, max_depth), area, True) for name in LIMB_TESTS[f"{HANDS[side]}_arm"]]
    return out + (_leg_hits(pp, side, max_depth) if with_legs else [])


def _figures(n: int, hits: Hits) -> tuple[Tensor, Tensor, Tensor]:
    """``(n,)`` how many points of ``hits`` (:func:`_hits`) are inside, the deepest and their volume."""
    count, deepest, total = torch.zeros(n), torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    for f, k, d, area, _ in hits:
        if len(f):
            count.index_add_(0, f, torch.ones(len(f)))
            total.index_add_(0, f, d * area[k])
            deepest = deepest.scatter_reduce(0, f, d, "amax")
    return count, deepest, total


def _leg_hits(pp: PosedParts, side: int, max_depth: float) -> Hits:
    """:func:`_hits` of the legs' points inside arm ``side`` alone."""
    arm = f"{HANDS[side]}_arm"
    return [(*_inside(pp, torch.from_numpy(p), arm, max_depth), a, False)
            for p, a in zip(pp.rb.leg_points, pp.rb.leg_area, strict=True)]  # fmt: skip


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
    lo, hi = pp.box(name)
    posed = pp.posed.contiguous()
    f, k = (torch.from_numpy(x) for x in rows_in_boxes(posed.numpy(), pts.numpy(), lo[:, 0].contiguous().numpy(),
                                                        hi[:, 0].contiguous().numpy()))  # fmt: skip
    if len(f) == 0:
        return empty
    at = posed[f, pts[k]]
    tree, boxes = pp.rb.trees[name], pp.tree_boxes(name, torch.unique(f))
    inside = winding_numbers(tree, boxes, f, at).abs() > 0.5
    f, k, at = f[inside], k[inside], at[inside]
    d, face = closest_triangles(tree, boxes, f, at, max_depth)
    return f, k, d, face, boxes


__all__ = ["arm_penetration", "arm_penetration_and_search", "arm_search_figures", "points_inside"]
