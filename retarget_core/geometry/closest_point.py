"""Closest points on triangles, exact and batched (Ericson, Real-Time Collision Detection 5.1.5): shared by the
hand-to-part distances (:mod:`retarget_core.contacts.hand_distance`) and the triangle tree
(:mod:`retarget_core.geometry.triangle_bvh`)."""

from __future__ import annotations

import torch
from torch import Tensor


def closest_points(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Closest points ``(N, 3)`` to ``p (N, 3)`` on triangles ``(a, b, c)`` each ``(N, 3)`` (Ericson 5.1.5;
    a triangle without area is handled through its edges)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    safe = torch.where(denom != 0, denom, torch.ones_like(denom))
    q = a + ab * (vb / safe)[:, None] + ac * (vc / safe)[:, None]

    def ratio(n: Tensor, d: Tensor) -> Tensor:
        return (n / torch.where(d != 0, d, torch.ones_like(d))).clamp(0.0, 1.0)[:, None]

    on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    q = torch.where(on_bc[:, None], b + (c - b) * ratio(d4 - d3, (d4 - d3) + (d5 - d6)), q)
    q = torch.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + ac * ratio(d2, d2 - d6), q)
    q = torch.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + ab * ratio(d1, d1 - d3), q)
    q = torch.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = torch.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = torch.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    flat = denom.abs() <= 1e-30 * (ab.norm(dim=-1) * ac.norm(dim=-1)).clamp_min(1e-300) + 1e-300
    if bool(flat.any()):
        q[flat] = _edge_points(p[flat], a[flat], b[flat], c[flat])
    return q


def _edge_points(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    def seg(x: Tensor, y: Tensor) -> Tensor:
        d = y - x
        t = ((p - x) * d).sum(-1) / (d * d).sum(-1).clamp_min(1e-300)
        return x + d * t.clamp(0, 1)[:, None]

    cands = torch.stack([seg(a, b), seg(b, c), seg(a, c)])
    k = (cands - p).norm(dim=-1).argmin(0)
    return cands[k, torch.arange(len(p))]


__all__ = ["closest_points"]
