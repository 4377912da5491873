"""Placing a retargeted motion on the floor by its mesh: the lowest foot vertex touches y = 0 where the
source stands.

The copy baseline (:mod:`retarget_core.copy_retarget`) sets the height by joint clearance: the target's foot
joints are as high above their rest heights as the scaled source's. On a body whose feet are shaped
differently (a bulky body's thicker soles, a source that itself floats) that leaves the mesh 1 to 4 cm above
the floor. :func:`place_on_floor` shifts the root vertically by one constant so that, on the frames where the
source has a foot planted, the lowest vertex of the target's feet is at the floor on average, then raises it
again if that would sink the feet elsewhere. Only the foot vertices are posed (linear blend skinning of a
subset), so it costs a few milliseconds on a 13k-vertex body.

The reference is per foot where the labels are: the lowest vertex of the planted foot itself, as the judged
float is measured (a copy's other foot may dip below the floor while it swings). :func:`stand_on_own_feet` puts
a source on the floor whatever height it came with: one that shows no planted foot where it came (a clip
re-grounded on frames where a pointed or swinging foot dips below the floor comes in several centimetres up) is
first set on the level where its still feet rest, instead of being placed on its lowest frames. "Before" is
placed on the source's planted feet as the judge reads them (:func:`planted_as_judged`: at 30 fps, on the
source as it stands in its file; :func:`before_labels`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.metrics.feet_acceptance import (
    REFERENCE_FPS,
    STEP_M,
    TOE_HEIGHT_M,
    foot_joint_pairs,
    foot_vertices,
    lowest_foot_heights,
    planted_feet,
)
from retarget_core.motion import Motion
from retarget_core.resample import resample

REFERENCE_HEIGHT_M = 1.80
# Height of the lowest foot vertex on planted frames after placement, at 1.80 m. Slightly above the floor:
# the judged float window is -0.5..+1.0 cm and ground penetration counts any vertex below y = 0, so aiming
# 2 mm up keeps the soles' frame-to-frame rocking (heel vs toe) from counting as penetration.
FLOAT_TARGET_M = 0.002
# "Without sinking elsewhere": the mean depth of the lowest foot vertex below the floor over all frames may
# not exceed this (1.80 m); the character is raised until it does not (the judged ground penetration is at
# most 5 mm: this leaves room for the rest of the mesh and for later stages).
MAX_MEAN_SINK_M = 0.003
# ...but never so far that the planted frames float more than this (1.80 m; the issue asks for the lowest foot
# vertex within 5 mm of the floor on planted frames).
MAX_FLOAT_M = 0.005
# Without any planted frame, the clip's lowest frames stand for the planted ones: this share of the frames
# with the lowest foot vertex (at least one frame).
LOWEST_FRAME_SHARE = 0.10
# The floor a source stands on: the lowest level where its still feet rest at least this share as often as at
# the level they rest on most (see resting_level).
FLOOR_BAND_SHARE = 0.5
# At most this many label-and-place rounds of stand_on_own_feet after the first placement.
STAND_ROUNDS = 3


def planted_by_foot(feet: FootContacts) -> Tensor:
    """``(F, 2)`` bool, left and right: the source has that foot planted (toe and heel both in contact; a rig
    without toes uses the heel alone)."""
    labels, avail = feet.labels, feet.available
    out = torch.zeros(labels.shape[0], 2, dtype=torch.bool)
    for side, (toe, heel) in enumerate(((0, 1), (2, 3))):
        if bool(avail[heel]):
            out[:, side] = labels[:, heel] & (labels[:, toe] if bool(avail[toe]) else True)
    return out


def planted_frames(feet: FootContacts) -> Tensor:
    """``(F,)`` bool: frames where the source has a foot planted (either foot; see :func:`planted_by_foot`)."""
    return planted_by_foot(feet).any(-1)


def lowest_foot_vertex(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F,)`` height of the lowest vertex of either foot (m)."""
    feet = foot_vertices(character, mapping)
    index = torch.cat([feet.left, feet.right])
    grot, gpos = motion.global_transforms()
    return character.lowest_heights(index, grot, gpos)


def _reference(lowest: Tensor, planted: Tensor) -> float:
    """The height (m) to put at the floor: the mean of ``lowest`` ((F,) per frame or (F, 2) per foot) over the
    ``planted`` entries ((F,) frames: both feet's lowest; (F, 2): each planted foot's own); without any, the
    clip's lowest frames."""
    if lowest.dim() == 2 and planted.dim() == 2 and bool(planted.any()):
        return float(lowest[planted].mean())
    frames = planted.any(-1) if planted.dim() == 2 else planted
    both = lowest.amin(-1) if lowest.dim() == 2 else lowest
    if bool(frames.any()):
        return float(both[frames].mean())
    k = max(1, int(round(LOWEST_FRAME_SHARE * both.numel())))
    return float(both.topk(k, largest=False).values.mean())


def floor_shift(lowest: Tensor, planted: Tensor, height: float) -> float:
    """The downward shift (m) that puts ``lowest`` (lowest foot vertex per frame ``(F,)``, or per frame and foot
    ``(F, 2)``) at the floor on the ``planted`` entries (``(F,)`` frames or ``(F, 2)`` feet; see module doc);
    negative raises."""
    scale = height / REFERENCE_HEIGHT_M
    reference = _reference(lowest, planted)
    shift = reference - FLOAT_TARGET_M * scale
    limit = MAX_MEAN_SINK_M * scale
    both = lowest.amin(-1) if lowest.dim() == 2 else lowest

    def sink(s: float) -> float:
        return float((s - both).clamp_min(0).mean())

    highest = reference - MAX_FLOAT_M * scale  # the smallest shift allowed (character highest)
    if sink(shift) > limit:
        # sink() grows with the shift: bisect between the highest allowed placement and this one.
        lo, hi = highest, shift
        if sink(lo) > limit:
            return lo
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if sink(mid) <= limit else (lo, mid)
        shift = lo
    return shift


def _raise(motion: Motion, mapping: JointMapping, dy: float) -> Motion:
    """``motion`` with its root (the Hips' topmost ancestor) ``dy`` metres higher in every frame."""
    hips = mapping.joints["Hips"]
    root = ([hips, *motion.skeleton.ancestors(hips)])[-1]
    translations = motion.translations.clone()
    translations[:, root, 1] += dy
    return Motion(motion.skeleton, motion.fps, motion.rotations, translations, motion.name)


def place_on_floor(character: Character, mapping: JointMapping, motion: Motion, planted: Tensor) -> Motion:
    """``motion`` (on ``character``'s skeleton) with its root shifted vertically by one constant so that the
    lowest foot vertex is at the floor where the source has a foot planted, without sinking the feet below it
    on the other frames. ``planted``: ``(F,)`` frames (both feet's lowest vertex counts, see
    :func:`planted_frames`) or ``(F, 2)`` per foot (each planted foot's own lowest vertex)."""
    if motion.num_frames == 0:
        return motion
    with torch.no_grad():
        lowest = lowest_foot_heights(character, mapping, motion)
    shift = floor_shift(lowest, planted[: motion.num_frames].bool(), character.height)
    return _raise(motion, mapping, -shift)


def still_feet(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F, 2)`` bool: each foot's toe and ankle moved at most the planted-foot step (1 cm per 1/30 s at
    1.80 m, as :mod:`retarget_core.metrics.feet_acceptance`) since the previous frame, whatever their height."""
    _, gpos = motion.global_transforms()
    if motion.num_frames < 2:
        return torch.ones(motion.num_frames, 2, dtype=torch.bool)
    limit = STEP_M * character.height / REFERENCE_HEIGHT_M * REFERENCE_FPS / motion.fps
    cols = []
    for toe, ankle in foot_joint_pairs(mapping):
        step = (gpos[1:, [toe, ankle]] - gpos[:-1, [toe, ankle]]).norm(dim=-1).amax(-1)  # (F-1,)
        cols.append(torch.cat([step[:1], step]) <= limit)
    return torch.stack(cols, dim=1)


def resting_level(lowest: Tensor, still: Tensor, width: float) -> float | None:
    """The height (m) of the floor the still feet rest on: over the ``still (F, 2)`` entries of ``lowest (F, 2)``,
    the median of the lowest ``width``-wide band that holds at least :data:`FLOOR_BAND_SHARE` of the busiest
    band's entries (a playground clip also stands on platforms; the floor is the lowest level it stands on);
    None without a still foot."""
    values = lowest[still].sort().values
    if values.numel() == 0:
        return None
    ends = torch.searchsorted(values, values + width, right=True)
    counts = ends - torch.arange(values.numel())
    i = int(torch.nonzero(counts >= FLOOR_BAND_SHARE * counts.max()).flatten()[0])
    return float(values[i : int(ends[i])].median())


def stand_on_own_feet(character: Character, mapping: JointMapping, motion: Motion) -> Motion:
    """``motion`` on ``character`` placed on the floor by its own planted feet (the source on its body: a
    studio's file stands on its floor, which the copy's joint-clearance height only approximates). Each foot
    planted as it stands (:func:`planted_as_judged`) has its lowest vertex put at the floor, and the labels are
    read again until they settle; a motion that shows no planted foot where it came (its height several
    centimetres off) is first set where its still feet rest (:func:`resting_level`)."""
    labels = planted_as_judged(character, mapping, motion)
    if not bool(labels.any()):
        scale = character.height / REFERENCE_HEIGHT_M
        with torch.no_grad():
            lowest = lowest_foot_heights(character, mapping, motion)
        level = resting_level(lowest, still_feet(character, mapping, motion), TOE_HEIGHT_M * scale)
        if level is not None:
            motion = _raise(motion, mapping, FLOAT_TARGET_M * scale - level)
            labels = planted_as_judged(character, mapping, motion)
    placed = place_on_floor(character, mapping, motion, labels)
    for _ in range(STAND_ROUNDS):
        again = planted_as_judged(character, mapping, placed)
        if torch.equal(again, labels):
            break
        labels = again
        placed = place_on_floor(character, mapping, placed, labels)
    return placed


def planted_as_judged(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F, 2)`` :func:`retarget_core.metrics.feet_acceptance.planted_feet` taken at the judge's 30 fps (its
    5-frame vote then spans 1/6 s, as the judge's does) and given to each frame of ``motion`` from the nearest
    30 fps frame: at 120 fps the vote spans 1/24 s and short pauses of a moving foot pass for planted."""
    if motion.num_frames == 0 or abs(motion.fps - REFERENCE_FPS) < 1e-6:
        return planted_feet(character, mapping, motion)
    labels = planted_feet(character, mapping, resample(motion, REFERENCE_FPS))
    nearest = (torch.arange(motion.num_frames) * (REFERENCE_FPS / motion.fps)).round().long()
    return labels[nearest.clamp(max=labels.shape[0] - 1)]


def before_labels(source_planted: Tensor | None, feet: FootContacts) -> Tensor:
    """``(F, 2)`` the (frame, foot) entries "before" is placed on: the source's planted feet as the judge reads
    them on the source as it stands (``source_planted``), or, where it has none, the detected foot contacts."""
    if source_planted is not None and bool(source_planted.any()):
        return source_planted.bool()
    return planted_by_foot(feet)


__all__ = [
    "before_labels", "floor_shift", "lowest_foot_vertex", "place_on_floor", "planted_as_judged", "planted_by_foot",
    "planted_frames", "resting_level", "stand_on_own_feet", "still_feet",
]  # fmt: skip
