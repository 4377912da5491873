"""Hand self-contact detection on a posed source body: hands resting on, sliding over or sunk into another part.

Paper 1 (section 3.4) calls two body groups in contact when their triangles intersect and their closest
vertices move together (velocity cosine above 0.9), or when their nearest vertices are closer than 0.2 cm. Read
literally on motion capture it misses most contacts a person would name: a hand resting on the belly or a
thigh is 0.3 to 1.5 cm away on the fitted body (the body is not the actor's), and a hand sunk into it is
rejected whenever the hand slides (sinking is the source body's error, not a pass-through). We use the
distance that the acceptance test uses instead (ACCEPTANCE.md "Hand self-contact"), measured exactly by
:mod:`retarget_core.contacts.hand_distance`: for each hand and each other part (head, torso, the other arm, each
leg; never the hand's own arm), the distance from the hand's vertices to the part's closed surface, 0 inside.

A (hand, part) pair is in contact on a frame when

1. the hand is within ``touch_m`` (1.5 cm at 1.80 m) of the part, or inside it; or
2. hysteresis: it is within ``release_m`` (2.5 cm) and belongs to a run of such frames that touches (1.), so a
   hand sliding over the body, lifting by a few millimetres, stays in contact; or
3. gap filling: it lies in a gap of at most ``fill_s`` (0.2 s) between two contact runs of the same pair and
   stays within ``far_m`` (3 cm, the acceptance test's "away from everything").

Thresholds were chosen on the shared clips (benchmarks/eval/contact_recall.py, docs/contacts.md): 1.5 cm is the
acceptance test's own source-contact distance; the 2.5 cm release equals the distance at which the acceptance
test calls a contact kept, so a contact never ends while the hand is still "touching" by that measure; nothing
is ever detected beyond 3 cm. The paper's velocity cosine is still computed (``cosine``) and the intersection
test is replaced by the inside test (``intersecting``: a hand vertex inside the part); neither gates detection.

Each contact keeps the ``pairs`` (3) closest (hand vertex, part vertex) pairs: distinct hand vertices nearest
the part's surface, each with the part vertex nearest its closest surface point; the transfer to the target
(:func:`retarget_core.contacts.correspondence.transfer_contacts`) maps these pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, BodyParts
from retarget_core.contacts.hand_distance import (
    REFERENCE_HEIGHT_M,
    HandDistanceParams,
    HandPartDistances,
    hand_part_distances,
)


@dataclass(frozen=True)
class SelfContactParams:
    """Thresholds of self-contact detection, lengths at a 1.80 m character (scaled to the body's height)."""

    # Touching: the acceptance test's source-contact distance (a hand resting on the fitted body reads 0 to 1.5 cm).
    touch_m: float = 0.015
    # Hysteresis: a touching run goes on while the hand stays this close (the acceptance test's "kept" distance).
    release_m: float = 0.025
    # Gaps between two contact runs up to this long are filled while the hand stays within far_m.
    fill_s: float = 0.2
    # Never a contact beyond this ("hands more than 3 cm from everything" must read no contact).
    far_m: float = 0.03
    reference_height_m: float = REFERENCE_HEIGHT_M
    pairs: int = 3
    # Velocity cosine (reported, paper 1): vertices slower than this (per 1/30 s at 1.80 m) count as still.
    still_speed_m: float = 0.002
    reference_fps: float = 30.0


@dataclass
class SelfContacts:
    """Detected hand contacts of one clip, one per (frame, hand, touched part).

    frame: ``(N,)`` frame of each contact; hand, other: ``(N,)`` segment indices (into ``part_names``): the hand
    and the segment of the part vertex of the closest pair; pairs: ``(N, P, 2)`` the P closest (hand vertex,
    part vertex) pairs; distance: ``(N, P)`` their vertex-to-vertex distances (m, on the source body);
    intersecting: ``(N,)`` a hand vertex lies inside the part; cosine: ``(N,)`` average velocity cosine
    similarity of the pairs (paper 1; information only); part: ``(N,)`` the touched part (index into
    ``part_clusters``, the body_parts clusters); source_distance: ``(N,)`` the hand's distance to that part's
    surface (m, 0 when inside); distances: the hand-to-part distances of every frame the contacts were found
    from (for the false contacts of the metrics).
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
    part: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    source_distance: Tensor = field(default_factory=lambda: torch.zeros(0))
    params: SelfContactParams = field(default_factory=SelfContactParams)
    part_clusters: tuple[str, ...] = CLUSTERS
    distances: HandPartDistances | None = None

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
        """Per (hand, touched part): number of frames in contact and the first and last such frame."""
        out: dict[tuple[int, int], list[int]] = {}
        for f, h, c in zip(self.frame.tolist(), self.hand.tolist(), self.part.tolist(), strict=True):
            out.setdefault((h, c), []).append(f)
        return [
            {"hand": self.part_names[h], "other": self.part_clusters[c], "frames": len(fs), "first": min(fs), "last": max(fs)}
            for (h, c), fs in sorted(out.items(), key=lambda kv: -len(kv[1]))
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


def _runs(mask: Tensor) -> tuple[Tensor, Tensor]:
    """Start and end (exclusive) ``(R,)`` of the runs of True in ``mask (F,)``."""
    m = torch.cat([torch.zeros(1, dtype=torch.int8), mask.to(torch.int8), torch.zeros(1, dtype=torch.int8)])
    step = m[1:] - m[:-1]
    return torch.nonzero(step == 1).flatten(), torch.nonzero(step == -1).flatten()


def contact_mask(distance: Tensor, height: float, fps: float, params: SelfContactParams | None = None) -> Tensor:
    """``(F, ...)`` bool from hand-to-part distances ``(F, ...)`` (m): the rules 1 to 3 of the module doc, along
    frames for every other index independently."""
    params = params or SelfContactParams()
    s = height / params.reference_height_m
    touch, release, far = params.touch_m * s, params.release_m * s, params.far_m * s
    fill = int(round(params.fill_s * fps))
    flat = distance.reshape(distance.shape[0], -1)
    out = torch.zeros_like(flat, dtype=torch.bool)
    for k in range(flat.shape[1]):
        d = flat[:, k]
        touching = d <= touch
        if not bool(touching.any()):
            continue
        on = touching.clone()
        starts, ends = _runs(d <= release)
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            if bool(touching[a:b].any()):
                on[a:b] = True
        starts, ends = _runs(on)
        for e, a in zip(ends[:-1].tolist(), starts[1:].tolist(), strict=True):
            if a - e <= fill and bool((d[e:a] <= far).all()):
                on[e:a] = True
        out[:, k] = on
    return out.reshape(distance.shape)


def _cosines(posed: Tensor, frame: Tensor, pairs: Tensor, still: float) -> Tensor:
    """Mean velocity cosine ``(N,)`` of each contact's pairs (velocities relative to the body's centroid)."""
    if len(frame) == 0:
        return torch.zeros(0)
    x = posed.detach().float()
    frames = frame.unique()
    prev = (frames - 1).clamp_min(0)
    nxt = (frames + 1).clamp_max(x.shape[0] - 1)
    vel = (x[nxt] - x[prev]) / (nxt - prev).clamp_min(1).to(x.dtype)[:, None, None]  # (U, V, 3)
    vel = vel - vel.mean(1, keepdim=True)  # walking is not a contact
    row = torch.searchsorted(frames, frame)
    va, vb = vel[row[:, None], pairs[..., 0]], vel[row[:, None], pairs[..., 1]]  # (N, P, 3)
    sa, sb = va.norm(dim=-1), vb.norm(dim=-1)
    cos = (va * vb).sum(-1) / (sa * sb).clamp_min(1e-12)
    cos = torch.where((sa < still) & (sb < still), 1.0, torch.where((sa < still) | (sb < still), 0.0, cos))
    return cos.mean(-1)


def contacts_from_distances(
    parts: BodyParts, posed: Tensor, distances: HandPartDistances, height: float, fps: float,
    params: SelfContactParams | None = None,
) -> SelfContacts:  # fmt: skip
    """The contacts of a clip from its hand-to-part distances (see the module doc)."""
    params = params or SelfContactParams()
    f_n = posed.shape[0]
    d = torch.where(distances.measured[None], distances.distance, torch.inf)
    on = contact_mask(d, height, fps, params) & torch.isfinite(d)
    frame, hi, part = torch.nonzero(on, as_tuple=True)
    pairs = distances.pairs[frame, hi, part, : params.pairs]  # (N, P, 2)
    hand_seg = torch.tensor([parts.find(h) if parts.find(h) is not None else -1 for h in distances.hands])
    x = posed.detach()
    pair_dist = (x[frame[:, None], pairs[..., 0]] - x[frame[:, None], pairs[..., 1]]).norm(dim=-1).float()
    still = params.still_speed_m * height / params.reference_height_m * params.reference_fps / fps
    return SelfContacts(
        num_frames=f_n,
        part_names=list(parts.names),
        frame=frame,
        hand=hand_seg[hi],
        other=parts.vertex_part[pairs[:, 0, 1]] if len(frame) else torch.zeros(0, dtype=torch.long),
        pairs=pairs,
        distance=pair_dist.reshape(len(frame), params.pairs),
        intersecting=distances.inside[frame, hi, part],
        cosine=_cosines(x, frame, pairs, still),
        part=part,
        source_distance=distances.distance[frame, hi, part].float(),
        params=params,
        part_clusters=tuple(distances.parts),
        distances=distances,
    )


def detect_self_contacts(
    parts: BodyParts,
    posed: Tensor,
    height: float,
    fps: float,
    params: SelfContactParams | None = None,
    *,
    rest_vertices: Tensor | None = None,
    distance_params: HandDistanceParams | None = None,
) -> SelfContacts:
    """Hand self-contacts of a posed body: ``posed (F, V, 3)`` vertices (e.g. ``Character.pose_vertices`` of the
    source body driven by the source motion), ``height`` of the body in metres, ``fps`` of the clip.
    ``rest_vertices (V, 3)`` only lays out the distance queries' chunks (the first frame when not given)."""
    params = params or SelfContactParams()
    distance_params = distance_params or HandDistanceParams(pairs=params.pairs)
    from retarget_core.contacts.hand_distance import hand_part_geometry

    ref = rest_vertices if rest_vertices is not None else (posed[0] if len(posed) else None)
    if ref is None:
        return contacts_from_distances(
            parts, posed, _no_distances(posed.shape[0], params.pairs), height, fps, params
        )  # fmt: skip
    geom = hand_part_geometry(parts, ref.detach(), height, distance_params)
    distances = hand_part_distances(None, parts, posed, distance_params, geom, height=height)
    return contacts_from_distances(parts, posed, distances, height, fps, params)


def _no_distances(frames: int, pairs: int) -> HandPartDistances:
    n_p = len(CLUSTERS)
    return HandPartDistances(
        ("LeftHand", "RightHand"), tuple(CLUSTERS), torch.full((frames, 2, n_p), torch.inf, dtype=torch.float64),
        torch.zeros(frames, 2, n_p, dtype=torch.bool), torch.full((frames, 2, n_p, pairs, 2), -1, dtype=torch.long),
        torch.full((frames, 2, n_p, pairs), torch.inf, dtype=torch.float64), torch.zeros(2, n_p, dtype=torch.bool),
        float("inf"),
    )  # fmt: skip


__all__ = [
    "SelfContactParams",
    "SelfContacts",
    "contact_mask",
    "contacts_from_distances",
    "detect_self_contacts",
    "vertex_velocities",
]
