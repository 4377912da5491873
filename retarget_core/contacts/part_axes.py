"""The way out of a part along its bones: per judged part (:data:`retarget_core.body_parts.CLUSTERS`), the bones of
its canonical joints, and for a point near the part the unit direction from the nearest point on those bones to it.

Why: a hand that grazes a part (a few millimetres off its surface, or inside it) has no reliable way out from its
nearest surface point: the gap between the two is shorter than the mesh's detail, and its direction flips from one
measure to the next (the hand contact stage pushed a walking Witch's hand off her thigh one way, then back the other,
for six passes). The direction away from the part's bone is defined wherever the point is off the bone itself.
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTER_OF, CLUSTERS
from retarget_core.canonical import CANONICAL_PARENT


def part_bones(joints: dict[str, int]) -> dict[str, Tensor]:
    """Per part of :data:`CLUSTERS`: ``(B, 2)`` skeleton joint indices of its bones, each mapped canonical joint of
    the part joined to its canonical parent when that is mapped and in the part too, and each joint alone (a
    bone of no length: a part of one mapped joint still has an axis point). ``joints``: canonical name -> index."""
    out: dict[str, Tensor] = {}
    for part in CLUSTERS:
        names = [n for n, c in CLUSTER_OF.items() if c == part and n in joints]
        pairs = [(joints[n], joints[n]) for n in names]
        pairs += [(joints[par], joints[n]) for n in names if (par := CANONICAL_PARENT.get(n)) in names]
        out[part] = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2)
    return out


def away_from_bones(points: Tensor, gpos: Tensor, bones: Tensor) -> Tensor:
    """``(F, K, 3)`` unit directions from the nearest point on ``bones (B, 2)`` (joint index pairs into ``gpos (F,
    J, 3)``, world positions) to each of ``points (F, K, 3)``; zero where there is no bone, the point is NaN or on
    a bone."""
    if len(bones) == 0:
        return torch.zeros_like(points)
    a, b = gpos[:, bones[:, 0]].to(points.dtype), gpos[:, bones[:, 1]].to(points.dtype)  # (F, B, 3)
    ab = (b - a)[:, None]  # (F, 1, B, 3)
    ap = points[:, :, None] - a[:, None]  # (F, K, B, 3)
    t = ((ap * ab).sum(-1) / ab.pow(2).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    off = ap - t[..., None] * ab  # (F, K, B, 3): from the nearest point on each bone to the point
    dist = off.norm(dim=-1)
    nearest = torch.nan_to_num(dist, nan=torch.inf).argmin(dim=-1)  # (F, K)
    way = off.gather(2, nearest[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
    return torch.nan_to_num(way / way.norm(dim=-1, keepdim=True).clamp_min(1e-9))


__all__ = ["away_from_bones", "part_bones"]
