"""How deep each hand is inside the parts the judge tests it against (ACCEPTANCE.md: a hand vertex is an arm
vertex; the arm is tested against the torso, the head, the other arm and the legs), and the way out: per frame,
hand and part, the deepest sampled hand vertex inside the part's closed mesh and its nearest surface point. The
hand contact stage (:mod:`retarget_core.refine.hand_contacts`) moves a hand out by it. Lengths in metres on the
body's own scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.contacts.arm_depth import points_inside
from retarget_core.contacts.hand_reach import PosedParts
from retarget_core.geometry.closest_point import closest_points
from retarget_core.metrics.acceptance_body import HANDS, LIMB_TESTS


def hand_tests(side: int) -> tuple[str, ...]:
    """The parts hand ``side`` (0 left, 1 right) is tested against: its arm's (:data:`LIMB_TESTS`)."""
    return LIMB_TESTS[f"{HANDS[side]}_arm"]


@dataclass
class HandDepth:
    """Per frame, hand and part of :func:`hand_tests` ``(n, 2, P)``: ``depth`` of the deepest sampled hand vertex
    inside the part (0: none; deeper than the cap: not read), and ``(n, 2, P, 3)`` that vertex (``hand_point``)
    and its nearest point on the part's surface (``surface_point``; NaN where ``depth`` is 0)."""

    depth: Tensor
    hand_point: Tensor
    surface_point: Tensor

    @staticmethod
    def empty(n: int) -> HandDepth:
        """No hand inside anything on ``n`` frames."""
        p_n = len(hand_tests(0))
        nan = torch.full((n, 2, p_n, 3), float("nan"), dtype=torch.float64)
        return HandDepth(torch.zeros(n, 2, p_n, dtype=torch.float64), nan, nan.clone())

    def out_moves(self, deeper_than: float) -> Tensor:
        """``(n, 2, 3)`` each hand's move out of the parts it is deeper than ``deeper_than`` in: the sum over
        parts of its deepest vertex's way to the surface."""
        way = torch.nan_to_num(self.surface_point - self.hand_point)
        return (way * (self.depth > deeper_than)[..., None]).sum(dim=2)


def hand_depths(pp: PosedParts, max_depth: float) -> HandDepth:
    """:class:`HandDepth` of the chunk of posed frames ``pp`` (each hand's sampled vertices
    ``pp.rb.hand_points``), read up to ``max_depth``."""
    out = HandDepth.empty(pp.posed.shape[0])
    for side in range(2):
        pts = torch.from_numpy(pp.rb.hand_points[side])
        for p_i, name in enumerate(hand_tests(side)):
            if len(pts):
                _deepest_inside(pp, pts, name, max_depth, out, side, p_i)
    return out


def _deepest_inside(pp: PosedParts, pts: Tensor, name: str, max_depth: float, out: HandDepth, side: int,
                    p_i: int) -> None:  # fmt: skip
    """Write into ``out[:, side, p_i]`` the deepest of ``pts (K,)`` inside part ``name`` per frame."""
    f, k, d, face, boxes = points_inside(pp, pts, name, max_depth)
    read = face >= 0  # deeper than max_depth: not read
    f, k, d, face = f[read], k[read], d[read], face[read]
    if len(f) == 0 or boxes is None:
        return
    n = pp.posed.shape[0]
    deepest = torch.zeros(n, dtype=torch.float64).scatter_reduce(0, f, d, "amax")
    tied = torch.nonzero(d == deepest[f]).flatten()  # one of each frame's deepest: the last
    pick = torch.full((n,), -1, dtype=torch.long).scatter_reduce(0, f[tied], tied, "amax")
    pick = pick[pick >= 0]
    f, k, face = f[pick], k[pick], face[pick]
    tri = pp.rb.trees[name].faces[face]
    row = f if boxes.rows is None else boxes.rows[f]  # the stored row of each frame's posed closed mesh
    point = pp.posed[f, pts[k]]
    out.depth[f, side, p_i] = deepest[f]
    out.hand_point[f, side, p_i] = point
    out.surface_point[f, side, p_i] = closest_points(point, *(boxes.vertices[row, tri[:, c]] for c in range(3)))


__all__ = ["HandDepth", "hand_depths", "hand_tests"]
