"""Which frames of a clip the metrics must measure, and which hand-to-part distances they must compute exactly.

- :func:`unchanged_frames`: frames where a motion poses the skeleton exactly as another one ("after" against
  "before"): their per-frame measures are copied from the other one's instead of measured again.
- :func:`hand_part_candidates`: per (frame, hand, part), whether a hand vertex came within the SDF grid margin
  (3 cm at 1.80 m) of a segment of that part in the penetration queries. A hand closer than the false-contact
  distance (1 cm) to a part, or inside it, always does, so the exact (KD-tree, point-triangle) hand-to-part
  distance is only needed on the frames where some candidate pair is far on the source (docs/metrics.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, HAND_SEGMENTS, BodyParts
from retarget_core.energy.sdf import PairSamples
from retarget_core.motion import Motion


@dataclass
class Reuse:
    """Measures of ``motion`` on the same character (e.g. "before"), to copy on the frames posed the same."""

    motion: Motion
    measures: object  # ClipMeasures (typed loosely: compute.py imports this module)


def unchanged_frames(motion: Motion, other: Motion | None) -> Tensor:
    """``(F,)`` bool: frames whose local rotations and translations equal ``other``'s exactly (all False when
    ``other`` is None, has another frame count or another skeleton size)."""
    f_n = motion.num_frames
    if other is None or other.num_frames != f_n or other.rotations.shape != motion.rotations.shape:
        return torch.zeros(f_n, dtype=torch.bool)
    same_rot = (motion.rotations == other.rotations).flatten(1).all(1)
    same_pos = (motion.translations == other.translations).flatten(1).all(1)
    return same_rot & same_pos


def hand_part_candidates(parts: BodyParts, samples: PairSamples, frames: int) -> Tensor:
    """``(frames, 2, P)`` bool, hands in :data:`HAND_SEGMENTS` order and parts in :data:`CLUSTERS` order: some
    vertex of the hand (dominant segment) was sampled against a segment of the part."""
    out = torch.zeros(frames * len(HAND_SEGMENTS) * len(CLUSTERS), dtype=torch.bool)
    hand_of_seg = torch.full((parts.num_parts,), -1, dtype=torch.long)
    for h, name in enumerate(HAND_SEGMENTS):
        if (s := parts.find(name)) is not None:
            hand_of_seg[s] = h
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    hand = hand_of_seg.index_select(0, parts.vertex_part.index_select(0, samples.vertex))
    ok = hand >= 0
    key = (samples.frame[ok] * len(HAND_SEGMENTS) + hand[ok]) * len(CLUSTERS) + cluster.index_select(
        0, samples.part[ok]
    )
    out[key] = True
    return out.view(frames, len(HAND_SEGMENTS), len(CLUSTERS))


def frame_chunks(frames: Tensor, chunk: int) -> list[Tensor]:
    """The frame indices ``frames (N,)`` in pieces of at most ``chunk``."""
    return [frames[s : s + chunk] for s in range(0, len(frames), chunk)]


__all__ = ["Reuse", "frame_chunks", "hand_part_candidates", "unchanged_frames"]
