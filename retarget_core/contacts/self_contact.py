"""Hand self-contact detection on a posed source mesh (paper 1, section 3.4).

Per frame, each hand group (vertices with a hand weight >= 0.5, fingers included) is tested against every
other group except its own forearm:

1. candidates: the groups' bounding boxes, grown by the distance threshold, overlap;
2. the groups intersect when any of their triangles intersect (box broad phase, exact narrow phase), and their
   nearest vertices are found (all pairs, on the vertices inside the other group's box);
3. the pair is a contact when they intersect and the average cosine similarity of the velocities of their
   closest vertex pairs exceeds 0.9 (they move together: a grip, a hand resting on the hips), or when they do
   not intersect and their nearest vertices are closer than 0.2 cm scaled from a 1.38 m character to this one
   (touching). Intersecting groups that do not move together are a pass-through, not a contact. (The paper
   states the two rules with "or"; read literally, the distance rule would accept every intersection, since
   intersecting surfaces are at distance zero, and the velocity rule would never matter.)
4. each contact keeps its 3 closest vertex pairs (distinct hand vertices).

Choices the paper leaves open: velocities are central differences of the posed vertices, taken relative to the
velocity of the body's centroid (in global coordinates, as the paper says, every part of a walking body moves
the same way and any two would agree); a vertex slower than
2 mm per 1/30 s (at 1.80 m) counts as still, two still vertices count as moving together (a hand resting on
the hips), one still and one moving as not; the cosine is averaged over the 10 closest pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from retarget_core.body_parts import HAND_SEGMENTS, BodyParts
from retarget_core.contacts.triangles import intersecting_pairs


@dataclass(frozen=True)
class SelfContactParams:
    """Thresholds of self-contact detection (paper 1 where it gives them)."""

    distance_m: float = 0.002
    distance_reference_height_m: float = 1.38
    cosine: float = 0.9
    still_speed_m: float = 0.002
    speed_reference_height_m: float = 1.80
    reference_fps: float = 30.0
    pairs: int = 3
    cosine_pairs: int = 10
    group_threshold: float = 0.5


@dataclass
class SelfContacts:
    """Detected hand contacts of one clip.

    frame: ``(N,)`` frame of each contact; hand, other: ``(N,)`` segment indices (into ``part_names``);
    pairs: ``(N, P, 2)`` the P closest (hand vertex, other vertex) pairs; distance: ``(N, P)`` their distances
    (m, on the source body); intersecting: ``(N,)`` whether the groups' triangles intersect;
    cosine: ``(N,)`` average velocity cosine similarity of the closest pairs.
    """

    num_frames: int
    part_names: list[str]
    frame: Tensor
    hand: Tensor
    other: Tensor
    pairs: Tensor
    distance: Tensor
    intersecting: Tensor
    cosine: Tensor
    params: SelfContactParams = field(default_factory=SelfContactParams)

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])

    def frames_with_contact(self) -> Tensor:
        """``(F,)`` bool: frames with at least one contact."""
        out = torch.zeros(self.num_frames, dtype=torch.bool)
        out[self.frame] = True
        return out

    def vertex_pairs(self) -> tuple[Tensor, Tensor, Tensor]:
        """Every constrained pair flattened: frame ``(M,)``, vertex i ``(M,)``, vertex j ``(M,)``."""
        p = self.pairs.shape[1] if self.count else 0
        return self.frame.repeat_interleave(p), self.pairs[..., 0].reshape(-1), self.pairs[..., 1].reshape(-1)

    def summary(self) -> list[dict[str, object]]:
        """Per (hand, other part): number of frames in contact and the first and last such frame."""
        out: dict[tuple[int, int], list[int]] = {}
        for f, h, o in zip(self.frame.tolist(), self.hand.tolist(), self.other.tolist(), strict=True):
            out.setdefault((h, o), []).append(f)
        return [
            {"hand": self.part_names[h], "other": self.part_names[o], "frames": len(fs), "first": min(fs), "last": max(fs)}
            for (h, o), fs in sorted(out.items(), key=lambda kv: -len(kv[1]))
        ]


def vertex_velocities(posed: Tensor) -> Tensor:
    """Per-frame vertex displacement ``(F, V, 3)`` by central differences (one-sided at the ends)."""
    if posed.shape[0] < 2:
        return torch.zeros_like(posed)
    vel = torch.empty_like(posed)
    vel[1:-1] = (posed[2:] - posed[:-2]) / 2
    vel[0] = posed[1] - posed[0]
    vel[-1] = posed[-1] - posed[-2]
    return vel


def _group_boxes(posed: np.ndarray, groups: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.stack([posed[:, g].min(axis=1) for g in groups], axis=1)
    hi = np.stack([posed[:, g].max(axis=1) for g in groups], axis=1)
    return lo, hi


def detect_self_contacts(
    parts: BodyParts,
    posed: Tensor,
    height: float,
    fps: float,
    params: SelfContactParams | None = None,
) -> SelfContacts:
    """Hand self-contacts of a posed body: ``posed (F, V, 3)`` vertices (e.g. ``Character.pose_vertices`` of the
    source body driven by the source motion), ``height`` of the body in metres, ``fps`` of the clip."""
    params = params or SelfContactParams()
    x_all = posed.detach().float().numpy()
    f_n = x_all.shape[0]
    thr = params.distance_m * height / params.distance_reference_height_m
    still = params.still_speed_m * height / params.speed_reference_height_m * params.reference_fps / fps
    names = parts.names
    weights = parts.weights.numpy()
    faces = parts.faces.numpy()
    groups = [np.nonzero(weights[:, s] >= params.group_threshold)[0] for s in range(len(names))]
    group_faces = [faces[(weights[faces, s] >= params.group_threshold).all(1)] for s in range(len(names))]
    present = [i for i, g in enumerate(groups) if len(g) > 0]
    hands = [parts.index(h) for h in HAND_SEGMENTS if parts.find(h) is not None and len(groups[parts.index(h)]) > 0]
    none = torch.zeros(0, dtype=torch.long)
    empty = SelfContacts(f_n, names, none, none, none, torch.zeros(0, params.pairs, 2, dtype=torch.long),
                         torch.zeros(0, params.pairs), torch.zeros(0, dtype=torch.bool), torch.zeros(0), params)  # fmt: skip
    if not hands or f_n == 0:
        return empty
    lo = np.zeros((f_n, len(names), 3), dtype=np.float32)
    hi = np.zeros((f_n, len(names), 3), dtype=np.float32)
    lo[:, present], hi[:, present] = _group_boxes(x_all, [groups[i] for i in present])
    vel = vertex_velocities(torch.from_numpy(x_all)).numpy()
    vel -= vel.mean(axis=1, keepdims=True)  # relative to the body's centroid: walking is not a contact
    rows: list[tuple[int, int, int, np.ndarray, np.ndarray, bool, float]] = []
    for h in hands:
        others = [g for g in present if g != h and g != parts.parent[h]]
        for g in others:
            near = ((lo[:, h] - thr <= hi[:, g]) & (hi[:, h] + thr >= lo[:, g])).all(-1)
            for f in np.nonzero(near)[0].tolist():
                found = _test_pair(x_all[f], vel[f], groups[h], groups[g], group_faces[h], group_faces[g], thr, still, params)
                if found is not None:
                    rows.append((f, h, g, *found))
    if not rows:
        return empty
    rows.sort(key=lambda r: (r[0], r[1], r[2]))
    return SelfContacts(
        f_n,
        names,
        torch.tensor([r[0] for r in rows]),
        torch.tensor([r[1] for r in rows]),
        torch.tensor([r[2] for r in rows]),
        torch.from_numpy(np.stack([r[3] for r in rows])).long(),
        torch.from_numpy(np.stack([r[4] for r in rows])).float(),
        torch.tensor([r[5] for r in rows]),
        torch.tensor([r[6] for r in rows]),
        params,
    )


def _max_edge(x: np.ndarray, faces: np.ndarray) -> float:
    if len(faces) == 0:
        return 0.0
    t = x[faces]
    return float(np.sqrt(((t - t[:, [1, 2, 0]]) ** 2).sum(-1).max()))


def _test_pair(
    x: np.ndarray, vel: np.ndarray, gh: np.ndarray, gg: np.ndarray, fh: np.ndarray, fg: np.ndarray,
    thr: float, still: float, params: SelfContactParams,
) -> tuple[np.ndarray, np.ndarray, bool, float] | None:  # fmt: skip
    """One frame, one (hand, other) group pair: the closest vertex pairs, their distances, whether the groups
    intersect and the velocity cosine, or None when the pair is not a contact."""
    xh, xg = x[gh], x[gg]
    lo_g, hi_g = xg.min(0) - thr, xg.max(0) + thr
    lo_h, hi_h = xh.min(0) - thr, xh.max(0) + thr
    sh = np.nonzero(((xh >= lo_g) & (xh <= hi_g)).all(-1))[0]
    sg = np.nonzero(((xg >= lo_h) & (xg <= hi_h)).all(-1))[0]
    if len(sh) == 0 or len(sg) == 0:
        return None  # no vertex of one group near the other's box: neither touching nor intersecting
    tree = cKDTree(xg[sg])
    dmin, arg = tree.query(xh[sh], k=1)
    closest = float(dmin.min())
    # Two meshes can only intersect where their vertices are within two edge lengths of each other.
    reach = 2.0 * max(_max_edge(x, fh), _max_edge(x, fg))
    if closest >= max(thr, reach):
        return None
    intersect = False
    if closest < reach:
        # Only triangles with a vertex within reach of the other group can take part in an intersection.
        near = np.zeros(len(x), dtype=bool)
        near[gh[sh[dmin < reach]]] = True
        dg, _ = cKDTree(xh[sh]).query(xg[sg], k=1, distance_upper_bound=reach)
        near[gg[sg[np.isfinite(dg)]]] = True
        fh_near, fg_near = fh[near[fh].any(1)], fg[near[fg].any(1)]
        intersect = len(intersecting_pairs(x, fh_near, fg_near, first_only=True)) > 0
    if not intersect and closest >= thr:
        return None
    order = np.argsort(dmin, kind="stable")
    k = min(params.cosine_pairs, len(order))
    va, vb = vel[gh[sh[order[:k]]]], vel[gg[sg[arg[order[:k]]]]]
    sa, sb = np.linalg.norm(va, axis=-1), np.linalg.norm(vb, axis=-1)
    cos = (va * vb).sum(-1) / np.maximum(sa * sb, 1e-12)
    cos = np.where((sa < still) & (sb < still), 1.0, np.where((sa < still) | (sb < still), 0.0, cos))
    mean_cos = float(cos.mean())
    # Intersecting groups touch when they move together; groups that do not intersect touch when their
    # nearest vertices are within the distance threshold.
    if intersect and mean_cos <= params.cosine:
        return None
    top = order[: params.pairs]
    pairs = np.stack([gh[sh[top]], gg[sg[arg[top]]]], axis=1)
    dist = dmin[top]
    if len(top) < params.pairs:  # fewer hand vertices than pairs asked for: repeat the closest
        pad = params.pairs - len(top)
        pairs = np.concatenate([pairs, np.repeat(pairs[:1], pad, axis=0)])
        dist = np.concatenate([dist, np.repeat(dist[:1], pad)])
    return pairs, dist, intersect, mean_cos


__all__ = ["SelfContactParams", "SelfContacts", "detect_self_contacts", "vertex_velocities"]
