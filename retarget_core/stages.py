"""The pipeline's switchable stages, in order: the one list that options, the pipeline, ``/v1/info`` and the
front end read. Light on purpose (no torch): the API imports it.

``contacts`` runs before the refinement stages (it finds what they must keep); the others live in
:mod:`retarget_core.refine`, one module each, and run in this order on the copy baseline.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StageInfo:
    """name: the option key; label and description: what the front end shows; default: on unless switched off;
    available: implemented in this version (unavailable stages are skipped with a note)."""

    name: str
    label: str
    description: str
    default: bool = True
    available: bool = True


STAGES: tuple[StageInfo, ...] = (
    StageInfo("contacts", "Contacts", "hand self-contacts and planted feet found on the source, carried to the target"),
    # recurrent and eso are on by default: before collisions and foot lock they keep the hands on the body where
    # the chain without them loses contacts (held-out split, 55 cases, 100 frames: worst contact preservation
    # 0.94 vs 0.86, mean 0.999 vs 0.989; other figures equal; about 20 ms/frame more; docs/model-recurrent.md).
    StageInfo("recurrent", "Recurrent network", "geometry-conditioned retargeting network"),
    StageInfo("eso", "Encoder-space optimisation", "test-time refinement of the network's states"),
    # learned_collisions: paper 2's per-limb model (docs/model-collisions.md); off by default: before the
    # optimisation resolver it lowers penetration (held-out, with foot lock: pen %v 0.141 vs 0.183) but loses
    # contacts (worst preservation 0.83 vs 0.86) and raises the end-effector error (2.49 vs 2.35 cm).
    StageInfo("learned_collisions", "Learned collision resolver", "paper 2's per-limb network turns limbs out of the body",
              default=False),
    StageInfo("collisions", "Collision resolution", "limbs out of the body by part SDFs, contacts kept"),
    StageInfo("foot_lock", "Foot lock", "planted feet held in place by two-bone IK"),
)
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)
REFINEMENT_STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES if s.name != "contacts")


def stage_info(name: str) -> StageInfo:
    """The entry of stage ``name`` (KeyError when unknown)."""
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(name)


__all__ = ["REFINEMENT_STAGE_NAMES", "STAGES", "STAGE_NAMES", "StageInfo", "stage_info"]
