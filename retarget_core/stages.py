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
    # recurrent and eso work but are off by default: on held-out clips they lower penetration and lengthen
    # contact distances / add foot skate (docs/model-recurrent.md); switch them on per job.
    StageInfo("recurrent", "Recurrent network", "geometry-conditioned retargeting network", default=False),
    StageInfo("eso", "Encoder-space optimisation", "test-time refinement of the network's states", default=False),
    # learned_collisions: paper 2's per-limb model (docs/model-collisions.md); off by default until the held-out
    # figures show it helps before the optimisation resolver.
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
