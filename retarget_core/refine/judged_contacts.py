"""The source's hand contacts as the judge counts them (ACCEPTANCE.md: a hand within 1.5 cm of a part on the
source), as contact instances of the target for the collision stage.

Why: the contact detector (:mod:`retarget_core.contacts`) finds the contacts a person would call contacts and
carries them to the target as vertex pairs; the judge also counts a hand that merely passes within 1.5 cm of a
part and loses it when the result's hand ends farther than 2.5 cm, and pushing an arm out of a thigh can carry
a hand that rests near the belly that far from it. These instances are only held near their part (within
``hold_m``), not pulled onto it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.body_parts import CLUSTERS, body_parts
from retarget_core.contacts.hand_distance import REFERENCE_HEIGHT_M, HandPartDistances, hand_part_distances
from retarget_core.context import RefineContext
from retarget_core.refine.collision_check import ContactInstances

SOURCE_CONTACT_M = 0.015  # ACCEPTANCE.md: a source contact is a hand within 1.5 cm of a part (at 1.80 m)


def _segment_distance(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``(F,)`` distance of points ``p (F, 3)`` to the segments ``a``-``b`` ``(F, 3)``."""
    ab = b - a
    t = (((p - a) * ab).sum(-1) / ab.pow(2).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (a + t[:, None] * ab - p).norm(dim=-1)


def _nearer_leg(ctx: RefineContext, gpos: Tensor, hand_joint: int) -> Tensor:
    """``(F,)`` cluster index of the leg (thigh and shin) nearer the hand joint in the target pose ``gpos``."""
    m = ctx.target_mapping.joints
    d = []
    for side in ("Left", "Right"):
        hip, knee, ankle = (m.get(f"{side}{n}") for n in ("UpLeg", "Leg", "Foot"))
        if hip is None or knee is None or ankle is None:
            d.append(torch.full((gpos.shape[0],), float("inf")))
            continue
        h = gpos[:, hand_joint]
        d.append(torch.minimum(_segment_distance(h, gpos[:, hip], gpos[:, knee]),
                               _segment_distance(h, gpos[:, knee], gpos[:, ankle])))  # fmt: skip
    left, right = CLUSTERS.index("left_leg"), CLUSTERS.index("right_leg")
    return torch.where(d[0] <= d[1], torch.tensor(left), torch.tensor(right))


def source_hand_distances(ctx: RefineContext) -> HandPartDistances:
    """The source's hand-to-part distances ``(F, 2, P)`` on its own body: the contact detector's
    (``ctx.self_contacts.distances``, the same definition as the judge's hand distances), measured here when the
    context has none."""
    found = ctx.self_contacts.distances
    if found is not None and found.num_frames == ctx.source_view.num_frames:
        return found
    body = ctx.source_body
    src_parts = body_parts(body, ctx.source_mapping)
    grot, gpos = ctx.source_view.global_transforms()
    with torch.no_grad():
        posed = body.pose_vertices(grot, gpos)
    return hand_part_distances(body, src_parts, posed)


def judged_source_instances(ctx: RefineContext, rotations: Tensor, translations: Tensor) -> ContactInstances:
    """The judge's source contacts at the target's frames as (frame, hand segment, cluster) instances; a contact
    with the legs goes to the leg nearer the hand in the target's pose ``rotations (F, J, 4)``,
    ``translations (F, J, 3)``. Empty when the source view's frames differ from the target's."""
    e = torch.zeros(0, dtype=torch.long)
    src = ctx.source_view
    if src.num_frames != ctx.num_frames or ctx.num_frames == 0:
        return ContactInstances(e, e, e)
    dist = source_hand_distances(ctx)
    near = dist.distance * (REFERENCE_HEIGHT_M / ctx.source_body.height) < SOURCE_CONTACT_M  # (F, 2, P)
    near &= dist.measured[None]
    if not bool(near.any()):
        return ContactInstances(e, e, e)
    with torch.no_grad():
        _, gpos = kinematics.forward_kinematics(ctx.target.skeleton.parents, rotations.float(), translations.float())
    legs = [dist.parts.index(n) for n in ("left_leg", "right_leg") if n in dist.parts]
    frames, hands, clusters = [], [], []

    def add(f: Tensor, seg: int, cluster: Tensor) -> None:
        frames.append(f)
        hands.append(torch.full_like(f, seg))
        clusters.append(cluster)

    for h, hand_name in enumerate(dist.hands):
        seg = ctx.parts.find(hand_name)
        joint = ctx.target_mapping.joints.get(hand_name)
        if seg is None or joint is None:
            continue
        on_legs = torch.nonzero(near[:, h, legs].any(-1)).flatten() if legs else torch.zeros(0, dtype=torch.long)
        if len(on_legs):
            add(on_legs, seg, _nearer_leg(ctx, gpos, joint)[on_legs])
        for c, part in enumerate(dist.parts):
            f = torch.nonzero(near[:, h, c]).flatten()
            if c not in legs and len(f):
                add(f, seg, torch.full_like(f, CLUSTERS.index(part)))
    if not frames:
        return ContactInstances(e, e, e)
    return ContactInstances(torch.cat(frames), torch.cat(hands), torch.cat(clusters))


def merged_instances(found: ContactInstances, judged: ContactInstances) -> tuple[ContactInstances, Tensor]:
    """``found`` followed by the instances of ``judged`` it lacks, and ``(N,)`` bool marking those added."""
    have = {(int(f), int(h), int(c)) for f, h, c in zip(found.frame, found.hand, found.cluster, strict=True)}
    rows = [(int(f), int(h), int(c)) for f, h, c in zip(judged.frame, judged.hand, judged.cluster, strict=True)]
    extra = sorted({r for r in rows if r not in have})
    data = torch.tensor(extra, dtype=torch.long).reshape(-1, 3)
    merged = ContactInstances(torch.cat([found.frame, data[:, 0]]), torch.cat([found.hand, data[:, 1]]),
                              torch.cat([found.cluster, data[:, 2]]))  # fmt: skip
    added = torch.cat([torch.zeros(found.count, dtype=torch.bool), torch.ones(len(extra), dtype=torch.bool)])
    return merged, added


__all__ = ["SOURCE_CONTACT_M", "judged_source_instances", "merged_instances", "source_hand_distances"]
