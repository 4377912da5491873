"""A body for a source motion that brings none (a bare BVH): a built-in MakeHuman body sized to its bones.

Approximate on purpose: the body's height is chosen so that its leg and hips-to-head lengths match the
source skeleton's on average; gender, weight and proportions stay average. Contacts measured on it are as
good as that fit (documented in the README).
"""

from __future__ import annotations

from functools import lru_cache

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.mapping import map_joints
from retarget_core.normalize import chain_length, leg_length
from retarget_core.skeleton import Skeleton

REFERENCE_HEIGHT_M = 1.75
MIN_HEIGHT_M, MAX_HEIGHT_M = 0.6, 2.4


def _trunk_length(skeleton: Skeleton, mapping: JointMapping) -> float:
    return chain_length(skeleton, mapping.joints["Hips"], mapping.joints["Head"])


@lru_cache(maxsize=1)
def _reference() -> tuple[float, float]:
    """Leg and trunk length of the neutral reference body at REFERENCE_HEIGHT_M."""
    body, mapping = _neutral_body(REFERENCE_HEIGHT_M)
    return leg_length(body.skeleton, mapping), _trunk_length(body.skeleton, mapping)


def _neutral_body(height: float) -> tuple[Character, JointMapping]:
    from retarget_core.bodies.makehuman import BodyParams, make_body

    body = make_body(BodyParams(name="source_body", gender=0.5, weight=0.5, muscle=0.5, height=round(height, 3)))
    return body, map_joints(body.skeleton)


def fitted_height(skeleton: Skeleton, mapping: JointMapping) -> float:
    """The standing height (m) of a neutral body whose bones best match ``skeleton`` (in metres)."""
    ref_leg, ref_trunk = _reference()
    ratio = 0.5 * (leg_length(skeleton, mapping) / ref_leg + _trunk_length(skeleton, mapping) / ref_trunk)
    return min(MAX_HEIGHT_M, max(MIN_HEIGHT_M, REFERENCE_HEIGHT_M * ratio))


def source_body_for(skeleton: Skeleton, mapping: JointMapping) -> tuple[Character, JointMapping]:
    """A neutral built-in body sized to the (normalised) source skeleton, and its joint mapping."""
    return _neutral_body(fitted_height(skeleton, mapping))
