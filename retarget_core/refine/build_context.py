"""A :class:`RefineContext` built from a motion file and a target, without the pipeline (tests, benchmarks,
stage development). The pipeline builds its own; this mirrors what it gives the stages: the copy baseline on
the target, the source on its own body, contacts detected on the source and carried to the target, foot labels
re-indexed to the target skeleton, and the target's part SDFs (cached per body)."""

from __future__ import annotations

from pathlib import Path

from retarget_core.contacts.correspondence import build_correspondence, no_contacts, transfer_contacts
from retarget_core.contacts.foot_contact import FOOT_JOINTS, FootContacts
from retarget_core.copy_retarget import copy_retarget
from retarget_core.evaluation import detect_source_contacts, part_sdf_for
from retarget_core.loading import load_character, load_motion
from retarget_core.refine.context import RefineContext
from retarget_core.resample import resample
from retarget_core.source_body import source_body_for


def context_from_files(motion_path: str | Path, target: str | Path, start: int = 0, frames: int | None = None,
                       fps: float | None = None) -> RefineContext:  # fmt: skip
    """The context of retargeting frames ``start:start+frames`` (after resampling to ``fps`` when given) of
    ``motion_path`` onto ``target`` (a file or ``builtin:<preset>``); ``context.before`` is the copy baseline."""
    source = load_motion(motion_path)
    if fps is not None:
        source.motion = resample(source.motion, fps)
    stop = None if frames is None else start + frames
    source.motion = source.motion.slice(start, stop)
    tgt = load_character(target)
    if source.source_character is not None:
        body, body_map = source.source_character.character, source.source_character.mapping
    else:
        body, body_map = source_body_for(source.motion.skeleton, source.mapping)
    before = copy_retarget(source.motion, source.mapping, tgt.character.skeleton, tgt.mapping)
    view = copy_retarget(source.motion, source.mapping, body.skeleton, body_map)
    found = detect_source_contacts(body, body_map, view)
    if found.self_contacts.count:
        constraints = transfer_contacts(found.self_contacts, build_correspondence(body, body_map, tgt.character, tgt.mapping))
    else:
        constraints = no_contacts(view.num_frames)
    feet = FootContacts(labels=found.feet.labels, joints=[tgt.mapping.joints.get(c, -1) for _, c in FOOT_JOINTS])
    parts, sdf = part_sdf_for(tgt.character, tgt.mapping)
    return RefineContext(
        target=tgt.character, target_mapping=tgt.mapping, parts=parts, sdf=sdf, source_body=body,
        source_mapping=body_map, source_view=view, self_contacts=found.self_contacts, constraints=constraints,
        feet=feet, before=before,
    )  # fmt: skip


__all__ = ["context_from_files"]
