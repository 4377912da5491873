"""The collision resolver's contact terms on a subset of points, batched over frames (one value for the whole
clip; the penetration term and the triples are in :mod:`retarget_core.geometry.triples`). Lengths in cm at a
1.80 m character, so the weights mean the same on every body:

- contact: ``relu(d - gap)^2`` with ``d`` the signed distance of a contact's nearest hand point to the part it
  touches (nearest segment of that part's cluster): a hand that left the surface is pulled back within ``gap``;
- contact pairs: a (hand vertex, body vertex) pair of a contact may come closer, not drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from retarget_core.energy.sdf import PartSDF, segment_distance
from retarget_core.geometry.triples import gather_rows, to_segment


@dataclass
class ContactTargets:
    """Hands to keep on (or bring to) the surface of the part they touch: contact instance ``k`` is met when the
    nearest of its hand's points lies on the surface of its touched cluster.

    frame, point, cluster, instance: ``(N,)`` per (instance, hand point) pair: optimised-frame index, index into
    the point set, touched cluster, instance index; active: ``(K,)`` 1 where the instance starts within reach;
    segments: per cluster index, its segments with grids."""

    frame: Tensor
    point: Tensor
    cluster: Tensor
    instance: Tensor
    active: Tensor
    segments: dict[int, list[int]]
    gap: Tensor | None = None  # (K,) m: each instance is met within this of its part (None: contact_energy's gap)
    tested: list[tuple[int, Tensor]] | None = None  # per segment, the pair rows measured against it (None: every
    # row against every segment of its cluster; :func:`near_contact_rows` keeps the ones that can be the nearest)

    @property
    def count(self) -> int:
        return int(self.active.shape[0])

    def segment_rows(self) -> list[tuple[int, Tensor]]:
        """Per segment ``j``, the pair rows ``(n,)`` whose distance to ``j`` is measured."""
        if self.tested is not None:
            return self.tested
        out: list[tuple[int, Tensor]] = []
        for c, segs in self.segments.items():
            sel = torch.nonzero(self.cluster == c).flatten()
            if len(sel):
                out.extend((j, sel) for j in segs)
        return out


def contact_row_points(targets: ContactTargets) -> list[tuple[int, Tensor, Tensor, Tensor]]:
    """Per measured segment ``j``: ``(j, rows (n,), frame (n,), point (n,))`` of the pair rows measured against it."""
    return [(j, sel, targets.frame.index_select(0, sel), targets.point.index_select(0, sel))
            for j, sel in targets.segment_rows()]  # fmt: skip


def contact_distances_rows(sdf: PartSDF, targets: ContactTargets, xs: list[Tensor],
                           mats: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """Signed distances ``(M,)`` (m) of the measured (pair row, segment) combinations, their rows and segments
    ``(M,)``, from the posed points ``xs[k] (n, 3)`` and transforms ``mats[k] (n, 3, 4)`` of each
    :func:`contact_row_points` entry."""
    measured = targets.segment_rows()
    if not measured:
        e = torch.zeros(0, dtype=torch.long)
        return torch.zeros(0), e, e
    ds = [segment_distance(sdf, j, to_segment(m, x)) for (j, _), x, m in zip(measured, xs, mats, strict=True)]
    return torch.cat(ds), torch.cat([sel for _, sel in measured]), torch.cat([torch.full_like(sel, j) for j, sel in measured])


def _row_distances(sdf: PartSDF, targets: ContactTargets, posed: Tensor,
                   seg_mats: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """:func:`contact_distances_rows` on ``posed (Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``."""
    rows = [gather_rows(posed, seg_mats, f, pt, j) for j, _, f, pt in contact_row_points(targets)]
    d, r, s = contact_distances_rows(sdf, targets, [x for x, _ in rows], [m for _, m in rows])
    return d.to(posed.dtype), r, s


def nearest_per_instance(targets: ContactTargets, d: Tensor, rows: Tensor) -> Tensor:
    """``(K,)`` the smallest of the row distances ``d (M,)`` per contact instance (rows ``(M,)``)."""
    out = d.new_full((targets.count,), float("inf"))
    return out.scatter_reduce(0, targets.instance.index_select(0, rows), d, "amin", include_self=True)


def instance_distance(sdf: PartSDF, targets: ContactTargets, posed: Tensor, seg_mats: Tensor) -> Tensor:
    """``(K,)`` signed distance (m) of each contact instance's nearest hand point to its touched cluster."""
    d, rows, _ = _row_distances(sdf, targets, posed, seg_mats)
    return nearest_per_instance(targets, d, rows)


def near_contact_rows(sdf: PartSDF, targets: ContactTargets, posed: Tensor, seg_mats: Tensor,
                      within: float) -> ContactTargets:  # fmt: skip
    """``targets`` measuring only the (pair row, segment) combinations within ``within`` (m) of their
    instance's nearest at the given pose: the only ones that can become the nearest during the next few steps
    (no gradients; the same distances while they hold)."""
    with torch.no_grad():
        d, rows, seg_of = _row_distances(sdf, targets, posed, seg_mats)
        inst = targets.instance.index_select(0, rows)
        best = d.new_full((targets.count,), float("inf")).scatter_reduce(0, inst, d, "amin", include_self=True)
        keep = d <= best.index_select(0, inst) + within
    tested = [(j, rows[keep & (seg_of == j)]) for j in torch.unique(seg_of[keep]).tolist()]
    return replace(targets, tested=tested)


def contact_energy_rows(targets: ContactTargets, d: Tensor, rows: Tensor, scale: float, gap: float = 0.0) -> Tensor:
    """Sum of ``relu(d - gap)^2`` (cm^2 at 1.80 m) over the active contact instances (a scalar) from the row
    distances ``d (M,)`` of :func:`contact_distances_rows`: a hand farther than ``gap`` (m; ``targets.gap`` per
    instance when set) from the part it touches is pulled back within it."""
    if targets.count == 0:
        return d.new_zeros(())
    g: Tensor | float = targets.gap if targets.gap is not None else gap
    return (((nearest_per_instance(targets, d, rows) - g).clamp_min(0.0) * (100.0 * scale)).pow(2) * targets.active).sum()


def contact_energy(sdf: PartSDF, targets: ContactTargets, posed: Tensor, seg_mats: Tensor, scale: float,
                   gap: float = 0.0) -> Tensor:  # fmt: skip
    """:func:`contact_energy_rows` on ``posed (Fa, P, 3)`` with segment transforms ``(Fa, S, 3, 4)``."""
    if targets.count == 0:
        return posed.new_zeros(())
    d, rows, _ = _row_distances(sdf, targets, posed, seg_mats)
    return contact_energy_rows(targets, d, rows, scale, gap)


@dataclass
class ContactPairs:
    """The contact constraints' vertex pairs ``(N,)``: optimised-frame index, the two point indices, and their
    distance on the input (m): a pair may come closer, not drift apart (the hand stays where it touched)."""

    frame: Tensor
    i: Tensor
    j: Tensor
    input_distance: Tensor

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])


def pair_distance(pairs: ContactPairs, posed: Tensor) -> Tensor:
    """``(N,)`` distance (m) of each pair's two posed points."""
    flat = posed.reshape(-1, 3)
    base = pairs.frame * posed.shape[1]
    return (flat.index_select(0, base + pairs.i) - flat.index_select(0, base + pairs.j)).norm(dim=-1)


def pair_energy_rows(pairs: ContactPairs, xi: Tensor, xj: Tensor, scale: float, allowance: float) -> Tensor:
    """Sum of ``relu(d - d_input - allowance)^2`` (cm^2 at 1.80 m) over the pairs (a scalar) posed at
    ``xi, xj (N, 3)``."""
    grow = (xi - xj).norm(dim=-1) - pairs.input_distance - allowance
    return (grow.clamp_min(0.0) * (100.0 * scale)).pow(2).sum()


def pair_energy(pairs: ContactPairs, posed: Tensor, scale: float, allowance: float) -> Tensor:
    """:func:`pair_energy_rows` on ``posed (Fa, P, 3)``."""
    if pairs.count == 0:
        return posed.new_zeros(())
    flat = posed.reshape(-1, 3)
    base = pairs.frame * posed.shape[1]
    return pair_energy_rows(pairs, flat.index_select(0, base + pairs.i), flat.index_select(0, base + pairs.j), scale, allowance)


__all__ = [
    "ContactPairs",
    "ContactTargets",
    "contact_distances_rows",
    "contact_energy",
    "contact_energy_rows",
    "contact_row_points",
    "instance_distance",
    "near_contact_rows",
    "nearest_per_instance",
    "pair_distance",
    "pair_energy",
    "pair_energy_rows",
]
