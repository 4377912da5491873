"""The pipeline's steps and switchable stages, in order: the one registry that the pipeline, its progress, the
job options, ``/v1/info``, the upload form, ``retarget eval`` and the docs read. Light on purpose (no torch): the
API imports it.

``contacts`` runs inside :func:`retarget_core.pipeline.prepare` (it finds what the refinement stages must keep);
the refinement stages live in :mod:`retarget_core.refine`, one module each, and run in this order on the copy
baseline. To add a stage: write its module with ``run(context, motion) -> StageOutcome`` and add its entry here.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StageInfo:
    """One switchable stage. name: the option key; label and description: what the front end shows; module: the
    module whose ``run`` implements a refinement stage (None: run by the pipeline itself); default: on unless
    switched off; weight: its share of a job's time, for the progress fraction; options: the job options
    (:class:`retarget_core.options.RetargetOptions` fields) it reads besides its switch; available: implemented
    in this version (unavailable stages are skipped with a note)."""

    name: str
    label: str
    description: str
    module: str | None
    weight: float
    default: bool = True
    options: tuple[str, ...] = ()
    available: bool = True


STAGES: tuple[StageInfo, ...] = (
    StageInfo("contacts", "Contacts", "hand self-contacts and planted feet found on the source, carried to the target",
              None, 0.06),
    StageInfo("recurrent", "Recurrent network", "geometry-conditioned retargeting network",
              "retarget_core.refine.recurrent", 0.02),
    StageInfo("eso", "Encoder-space optimisation", "test-time refinement of the network's states",
              "retarget_core.refine.eso", 0.07, options=("eso_iterations",)),
    StageInfo("learned_collisions", "Learned collision resolver", "paper 2's per-limb network turns limbs out of the body",
              "retarget_core.refine.collision_model", 0.05, default=False),
    StageInfo("collisions", "Collision resolution", "limbs out of the body by part SDFs, contacts kept",
              "retarget_core.refine.collisions", 0.25),
    StageInfo("foot_lock", "Foot lock", "planted feet held in place by two-bone IK",
              "retarget_core.refine.foot_lock", 0.01),
    StageInfo("floor", "Floor", "the body lifted, with least jerk, where it sinks below the floor",
              "retarget_core.refine.floor", 0.01),
    StageInfo("hand_contacts", "Hand contacts", "hands onto the parts they touch in the source, clear of the others",
              "retarget_core.refine.hand_contacts", 0.1),
    StageInfo("arm_swivel", "Elbow swivel", "arms turned about the shoulder-wrist line out of the body, hands kept",
              "retarget_core.refine.arm_swivel", 0.24),
    StageInfo("fingers", "Finger clearance", "fingers resting on the body turned onto its surface, not into it",
              "retarget_core.refine.fingers", 0.01),
    StageInfo("props", "Props above the floor", "a prop on its own bone (a staff, a sword) turned at its grip above the floor",
              "retarget_core.refine.props", 0.01),
)  # fmt: skip
"""Why each default stands: docs/results.md (the held-out evaluation of the default chain and its variants)."""

PREPARE_STEPS: dict[str, float] = {"read": 0.04, "copy": 0.02, "body": 0.03}
"""The pipeline's fixed steps before the refinement stages, with their share of a job's time."""

PREPARE_ORDER: tuple[str, ...] = ("read", "copy", "contacts", "body")
"""What :func:`retarget_core.pipeline.prepare` runs, in order (``contacts`` is a switchable stage)."""

FINISH_STEPS: dict[str, float] = {"metrics": 0.1, "write": 0.03}
"""The fixed steps after the refinement stages, with their share of a job's time."""

STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)
REFINEMENT_STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES if s.module is not None)


def stage_info(name: str) -> StageInfo:
    """The entry of stage ``name`` (KeyError when unknown)."""
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(name)


def progress_weight(name: str) -> float:
    """The share of a job's time that step or stage ``name`` takes (0 for an unknown name)."""
    if name in PREPARE_STEPS:
        return PREPARE_STEPS[name]
    if name in FINISH_STEPS:
        return FINISH_STEPS[name]
    return stage_info(name).weight if name in STAGE_NAMES else 0.0


__all__ = [
    "FINISH_STEPS",
    "PREPARE_ORDER",
    "PREPARE_STEPS",
    "REFINEMENT_STAGE_NAMES",
    "STAGES",
    "STAGE_NAMES",
    "StageInfo",
    "progress_weight",
    "stage_info",
]
