"""A realistic :class:`RefineContext` without the pipeline: source on its body, copy placed on the floor,
source contacts, the target's parts and SDFs. Used by the refinement tests (benchmarks use retarget_core.cases)."""

from __future__ import annotations

from dataclasses import dataclass

from retarget_core.body_cache import part_sdf_for
from retarget_core.body_parts import body_parts
from retarget_core.contacts.correspondence import build_correspondence, no_contacts, transfer_contacts
from retarget_core.contacts.foot_contact import FOOT_JOINTS, FootContacts
from retarget_core.context import RefineContext
from retarget_core.copy_retarget import copy_retarget
from retarget_core.loading import LoadedCharacter, LoadedMotion
from retarget_core.measure import SourceContactResult, detect_source_contacts
from retarget_core.metrics.feet_acceptance import planted_feet, toe_heights
from retarget_core.motion import Motion
from retarget_core.placement import place_on_floor, planted_frames
from retarget_core.source_body import source_body_for


@dataclass
class Harness:
    context: RefineContext
    source_view: Motion
    found: SourceContactResult


def make_context(
    source: LoadedMotion, target: LoadedCharacter, *, place: bool = True, contacts: bool = False, sdf: bool = True
) -> Harness:
    """The context of ``source`` retargeted onto ``target`` (``before`` placed on the floor unless ``place``
    is False); hand contacts are carried to the target only when ``contacts``. ``sdf=False`` leaves the part
    SDFs out (16 s on a 13k-vertex body) for tests of stages that do not read them."""
    if source.source_character is not None:
        body, body_map = source.source_character.character, source.source_character.mapping
    else:
        body, body_map = source_body_for(source.motion.skeleton, source.mapping)
    view = copy_retarget(source.motion, source.mapping, body.skeleton, body_map)
    char, tmap = target.character, target.mapping
    before = copy_retarget(source.motion, source.mapping, char.skeleton, tmap)
    found = detect_source_contacts(body, body_map, view)
    feet = FootContacts(labels=found.feet.labels, joints=[tmap.joints.get(c, -1) for _, c in FOOT_JOINTS])
    if place:
        before = place_on_floor(char, tmap, before, planted_frames(feet))
    if sdf:
        parts, part_sdf = part_sdf_for(char, tmap)
    else:
        parts, part_sdf = body_parts(char, tmap), None
    if contacts and found.self_contacts.count:
        constraints = transfer_contacts(found.self_contacts, build_correspondence(body, body_map, char, tmap))
    else:
        constraints = no_contacts(before.num_frames)
    ctx = RefineContext(
        target=char, target_mapping=tmap, parts=parts, sdf=part_sdf,  # type: ignore[arg-type]
        source_body=body, source_mapping=body_map, source_view=view, self_contacts=found.self_contacts,
        constraints=constraints, feet=feet, planted=planted_feet(body, body_map, view),
        toe_heights=toe_heights(body, body_map, view), before=before,
    )  # fmt: skip
    return Harness(ctx, view, found)
