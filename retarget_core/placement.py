"""Placing a retargeted motion on the floor by its mesh: the lowest foot vertex touches y = 0 where the
source stands.

The copy baseline (:mod:`retarget_core.copy_retarget`) sets the height by joint clearance: the target's foot
joints are as high above their rest heights as the scaled source's. On a body whose feet are shaped
differently (a bulky body's thicker soles, a source that itself floats) that leaves the mesh 1 to 4 cm above
the floor. :func:`place_on_floor` shifts the root vertically by one constant so that, on the frames where the
source has a foot planted, the lowest vertex of the target's feet is at the floor on average, then raises it
again if that would sink the feet elsewhere. Only the foot vertices are posed (linear blend skinning of a
subset), so it costs a few milliseconds on a 13k-vertex body.
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.metrics.feet_acceptance import foot_vertices
from retarget_core.motion import Motion

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


def planted_frames(feet: FootContacts) -> Tensor:
    """``(F,)`` bool: frames where the source has a foot planted (toe and heel both in contact, either foot;
    a rig without toes uses the heel alone)."""
    labels, avail = feet.labels, feet.available
    out = torch.zeros(labels.shape[0], dtype=torch.bool)
    for toe, heel in ((0, 1), (2, 3)):
        if bool(avail[heel]):
            out |= labels[:, heel] & (labels[:, toe] if bool(avail[toe]) else True)
    return out


def lowest_foot_vertex(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F,)`` height of the lowest vertex of either foot (m)."""
    feet = foot_vertices(character, mapping)
    index = torch.cat([feet.left, feet.right])
    grot, gpos = motion.global_transforms()
    return character.pose_vertex_subset(index, grot, gpos)[..., 1].amin(-1)


def floor_shift(lowest: Tensor, planted: Tensor, height: float) -> float:
    """The downward shift (m) that puts ``lowest (F,)`` (lowest foot vertex per frame) at the floor on
    ``planted (F,)`` frames (see module doc); negative raises."""
    scale = height / REFERENCE_HEIGHT_M
    if bool(planted.any()):
        reference = float(lowest[planted].mean())
    else:
        k = max(1, int(round(LOWEST_FRAME_SHARE * lowest.numel())))
        reference = float(lowest.topk(k, largest=False).values.mean())
    shift = reference - FLOAT_TARGET_M * scale
    limit = MAX_MEAN_SINK_M * scale

    def sink(s: float) -> float:
        return float((s - lowest).clamp_min(0).mean())

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


def place_on_floor(character: Character, mapping: JointMapping, motion: Motion, planted: Tensor) -> Motion:
    """``motion`` (on ``character``'s skeleton) with its root shifted vertically by one constant so that the
    lowest foot vertex is at the floor on the ``planted (F,)`` frames (where the source has a foot planted;
    see :func:`planted_frames`), without sinking the feet below it on the other frames."""
    if motion.num_frames == 0:
        return motion
    with torch.no_grad():
        lowest = lowest_foot_vertex(character, mapping, motion)
    shift = floor_shift(lowest, planted[: motion.num_frames].bool(), character.height)
    hips = mapping.joints["Hips"]
    root = ([hips, *motion.skeleton.ancestors(hips)])[-1]
    translations = motion.translations.clone()
    translations[:, root, 1] -= shift
    return Motion(motion.skeleton, motion.fps, motion.rotations, translations, motion.name)


__all__ = ["floor_shift", "lowest_foot_vertex", "place_on_floor", "planted_frames"]


def stand_on_own_feet(character: Character, mapping: JointMapping, motion: Motion) -> Motion:
    """``motion`` on ``character`` placed on the floor by its own planted feet (the source on its body: a
    studio's file stands on its floor, which the copy's joint-clearance height only approximates; foot
    contacts are then read off the motion as it stands)."""
    from retarget_core.contacts.foot_contact import detect_foot_contacts

    _, gpos = motion.global_transforms()
    _, rest = character.skeleton.rest_global()
    feet = detect_foot_contacts(gpos, rest, mapping, character.height, motion.fps)
    return place_on_floor(character, mapping, motion, planted_frames(feet))

