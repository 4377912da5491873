"""All-vertex penetration and contact figures per frame: what the collision stage's broad phase, finishing pass
and never-worse check read (the same blended-SDF depths as :mod:`retarget_core.metrics`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.body_parts import CLUSTERS
from retarget_core.character import Character
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.energy.sdf import PairSamples, PartSDF, sample_pairs, segment_matrices, vertex_depths
from retarget_core.metrics.depth import VertexDepths


@dataclass
class ContactInstances:
    """Distinct (frame, hand segment, touched cluster) contacts of the target: ``frame``, ``hand``,
    ``cluster`` ``(N,)`` (hand: segment index of the target's parts; cluster: index into :data:`CLUSTERS`)."""

    frame: Tensor
    hand: Tensor
    cluster: Tensor
    gap: Tensor | None = None  # (N,) m: how close to its part the hand is pulled (None: the stage's default)

    @property
    def count(self) -> int:
        return int(self.frame.shape[0])


def contact_instances(sdf: PartSDF, constraints: ContactConstraints) -> ContactInstances:
    """The contacts of ``constraints`` as distinct (frame, hand, cluster), by part name on the target."""
    parts = sdf.parts
    rows: set[tuple[int, int, int]] = set()
    for f, h, o in zip(constraints.frame.tolist(), constraints.hand.tolist(), constraints.other.tolist(), strict=True):
        hs = parts.find(constraints.part_names[h])
        os_ = parts.find(constraints.part_names[o])
        if hs is None or os_ is None:
            continue
        rows.add((f, hs, parts.cluster[os_]))
    data = torch.tensor(sorted(rows), dtype=torch.long).reshape(-1, 3)
    return ContactInstances(data[:, 0], data[:, 1], data[:, 2])


@dataclass
class FrameCheck:
    """Per checked frame ``(n,)``: penetration volume (m^3, sum of vertex area x depth), deepest vertex (m),
    penetrating vertex count (depth above the tolerance); ``depth`` every vertex's weighted depth, its nonzero
    entries only (rows: positions in ``frames``; a dense ``(n, V)`` is 380 MB for 1,000 frames of 95k vertices);
    ``contact (N,)`` each contact instance's hand-to-part distance (m, 0 inside, the grid margin when farther;
    NaN for instances outside the checked frames)."""

    frames: Tensor
    volume: Tensor
    max_depth: Tensor
    count: Tensor
    depth: VertexDepths
    contact: Tensor
    flagged: Tensor | None = None  # (n,) frames the measuring stage itself reads as worse (None: none)
    excused: Tensor | None = None  # (n,) frames whose deeper penetration the stage accepts for what it gained there


def check_frames(character: Character, sdf: PartSDF, rotations: Tensor, translations: Tensor, frames: Tensor,
                 contacts: ContactInstances, tolerance: float, chunk: int = 64,
                 allowed: Tensor | None = None) -> FrameCheck:  # fmt: skip
    """Pose the body's vertices (accessories left out) at clip ``frames (n,)`` of the local ``rotations (F, J,
    4)`` / ``translations (F, J, 3)`` and measure them (no gradients); ``allowed (S, S)``: the segment pairs
    measured (default ``sdf.allowed``; a contact's hand and touched part must be among them)."""
    parts = sdf.parts
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    n = len(frames)
    v_n = character.num_vertices
    vol, mx, cnt = torch.zeros(n), torch.zeros(n), torch.zeros(n)
    depth: list[VertexDepths] = []
    contact = torch.full((contacts.count,), float("nan"))
    pos_of = torch.full((rotations.shape[0],), -1, dtype=torch.long)
    pos_of[frames] = torch.arange(n)
    c_pos = pos_of[contacts.frame] if contacts.count else torch.zeros(0, dtype=torch.long)
    area = sdf.vertex_area
    body = None if parts.body is None else torch.nonzero(parts.body).flatten()  # accessories are never tested
    with torch.no_grad():
        for s in range(0, n, chunk):
            fr = frames[s : s + chunk]
            grot, gpos = kinematics.forward_kinematics(character.skeleton.parents, rotations[fr], translations[fr])
            verts = character.pose_vertices(grot, gpos) if body is None else character.pose_rows(body, grot, gpos)
            mats = segment_matrices(character, parts, grot, gpos)
            samples = sample_pairs(sdf, verts, mats, allowed, vertices=body)
            d = vertex_depths(sdf, samples, len(fr))
            depth.append(VertexDepths.from_dense(d, torch.arange(s, s + len(fr)), n))
            vol[s : s + len(fr)] = (d * area).sum(-1)
            mx[s : s + len(fr)] = d.amax(-1)
            cnt[s : s + len(fr)] = (d > tolerance).sum(-1).float()
            if contacts.count:
                sel = torch.nonzero((c_pos >= s) & (c_pos < s + len(fr))).flatten()
                if len(sel):
                    contact[sel] = _contact_distance(sdf, samples, contacts, sel, c_pos[sel] - s, cluster)
    return FrameCheck(frames, vol, mx, cnt, VertexDepths.concat(depth, n, v_n), contact)


def _contact_distance(sdf: PartSDF, samples: PairSamples, contacts: ContactInstances, sel: Tensor, local_frame: Tensor,
                      cluster: Tensor) -> Tensor:  # fmt: skip
    """Hand-to-cluster distance of contact instances ``sel`` (local frame indices into the samples' chunk)."""
    parts = sdf.parts
    s_n, c_n = parts.num_parts, len(CLUSTERS)
    f_n = int(local_frame.max()) + 1
    vpart = parts.vertex_part.index_select(0, samples.vertex)
    key = (samples.frame * s_n + vpart) * c_n + cluster.index_select(0, samples.part)
    table = samples.distance.new_full((max(f_n, int(samples.frame.max()) + 1 if len(samples.frame) else 1) * s_n * c_n,), sdf.margin)
    table = table.scatter_reduce(0, key, samples.distance.clamp(0.0, sdf.margin), "amin", include_self=True)
    q = (local_frame * s_n + contacts.hand[sel]) * c_n + contacts.cluster[sel]
    return table.index_select(0, q)


class WorseLimits(Protocol):
    """What makes a frame worse than before (lengths at 1.80 m): the stages' (frozen) parameters carry these.
    worse_volume_fraction and worse_volume_m3: penetration volume grown by more than both; worse_depth_m: the
    deepest vertex this much deeper; contact_ok_m: a contact closer than this counts as kept."""

    @property
    def worse_volume_fraction(self) -> float: ...
    @property
    def worse_volume_m3(self) -> float: ...
    @property
    def worse_depth_m(self) -> float: ...
    @property
    def contact_ok_m(self) -> float: ...


def worse_frames(before: FrameCheck, after: FrameCheck, contacts: ContactInstances, limits: WorseLimits,
                 scale: float) -> Tensor:  # fmt: skip
    """``(n,)`` bool over ``after.frames``: penetration or a contact got worse than in ``before`` (all frames), or
    ``after`` flags the frame; ``scale`` turns body lengths into lengths at 1.80 m."""
    idx = after.frames
    vol_b = before.volume[idx] * scale**3
    grow = after.volume * scale**3 - vol_b
    worse = grow > torch.clamp(limits.worse_volume_fraction * vol_b, min=limits.worse_volume_m3)
    worse |= (after.max_depth - before.max_depth[idx]) * scale > limits.worse_depth_m
    if after.excused is not None:
        worse &= ~after.excused
    if after.flagged is not None:
        worse |= after.flagged
    if contacts.count:
        ok = limits.contact_ok_m / scale
        bad = (after.contact > torch.clamp(before.contact, min=ok)) & ~torch.isnan(after.contact)
        pos_of = torch.full((len(before.frames),), -1, dtype=torch.long)
        pos_of[idx] = torch.arange(len(idx))
        hit = pos_of[contacts.frame[bad]]
        worse[hit[hit >= 0]] = True
    return worse


CONTACT_KEPT_M = 0.025  # ACCEPTANCE.md: a source contact is kept when the result's distance is below 2.5 cm


def stage_figures(before: FrameCheck, after: FrameCheck, contacts: ContactInstances, v_n: int,
                  scale: float) -> dict[str, Any]:  # fmt: skip
    """A collision stage's report figures: penetration and contacts before and after (at 1.80 m; ``v_n``
    vertices; 0 for a clip without frames)."""

    def pen(c: FrameCheck) -> dict[str, float]:
        if len(c.max_depth) == 0:
            return {"penetrating_vertices_percent": 0.0, "max_depth_cm": 0.0, "frames_deeper_than_1cm_percent": 0.0}
        return {
            "penetrating_vertices_percent": round(float(c.count.mean() / v_n * 100.0), 4),
            "max_depth_cm": round(float(c.max_depth.max() * scale * 100.0), 3),
            "frames_deeper_than_1cm_percent": round(float((c.max_depth * scale > 0.01).float().mean() * 100.0), 2),
        }

    out: dict[str, Any] = {"penetration_before": pen(before), "penetration_after": pen(after)}
    if contacts.count:
        kept = CONTACT_KEPT_M / scale
        out["contacts"] = {
            "instances": contacts.count,
            "kept_before": round(float((before.contact < kept).float().mean()), 4),
            "kept_after": round(float((after.contact < kept).float().mean()), 4),
            "mean_distance_before_cm": round(float(before.contact.mean() * scale * 100.0), 3),
            "mean_distance_after_cm": round(float(after.contact.mean() * scale * 100.0), 3),
        }
    return out


__all__ = [
    "CONTACT_KEPT_M",
    "stage_figures",
    "ContactInstances",
    "FrameCheck",
    "WorseLimits",
    "check_frames",
    "contact_instances",
    "worse_frames",
]
