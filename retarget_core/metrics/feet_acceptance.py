"""The feet figures of ../shared/ACCEPTANCE.md, as the independent judge defines them.

A foot (left, right) is planted on a frame when its toe joint is at most 3 cm above the toe's own rest height
and moved at most 1 cm since the last frame, and its ankle (the ``Foot`` joint) moved at most 1 cm; then a
5-frame majority vote. Lengths are at a 1.80 m character (each body by its own rest mesh height) and per
1/30 s. From those labels:

- foot accuracy: agreement of the result's labels ``(F, 2)`` with the source's;
- skate: mean horizontal speed of toe and ankle (cm per 1/30 s) on (frame, foot) where the source foot is
  planted;
- ground penetration: mean over frames of how far the lowest vertex of the whole mesh is below y = 0;
- float: mean height of the lowest foot vertex on source-planted frames. Foot vertices are those whose
  dominant segment is ``Foot`` or ``ToeBase`` (:mod:`retarget_core.body_parts`). ``float_cm`` takes, per
  (frame, foot) with the source foot planted, the lowest vertex of that foot; ``float_any_cm`` takes, per
  frame with either source foot planted, the lowest vertex of both feet (the judge's wording allows both).

This differs from :func:`retarget_core.contacts.foot_contact.detect_foot_contacts` (four columns toe/heel,
a window that only fills gaps) on purpose: it is the judge's definition, per foot and with a true majority.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from retarget_core.body_parts import BodyParts, body_parts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.motion import Motion

REFERENCE_HEIGHT_M = 1.80  # every length of ACCEPTANCE.md is at a 1.80 m character
REFERENCE_FPS = 30.0  # and every per-frame speed per 1/30 s
TOE_HEIGHT_M = 0.03  # toe joint at most this far above its rest height (ACCEPTANCE.md)
STEP_M = 0.01  # toe and ankle moved at most this far since the previous frame (ACCEPTANCE.md)
MAJORITY_WINDOW = 5  # frames of the majority vote (ACCEPTANCE.md)
SIDES: tuple[str, ...] = ("Left", "Right")


@dataclass(frozen=True)
class FootVertices:
    """Vertex indices ``(N,)`` of each foot (dominant segment Foot or ToeBase), left then right."""

    left: Tensor
    right: Tensor

    def sides(self) -> tuple[Tensor, Tensor]:
        return self.left, self.right


def foot_vertices(character: Character, mapping: JointMapping) -> FootVertices:
    """The vertices of each foot: those whose dominant canonical segment is that side's Foot or ToeBase."""
    return foot_vertices_of(body_parts(character, mapping))


def foot_vertices_of(parts: BodyParts) -> FootVertices:
    """:func:`foot_vertices` from a character's body parts."""
    out = []
    for side in SIDES:
        segs = [parts.index(n) for n in (f"{side}Foot", f"{side}ToeBase") if parts.find(n) is not None]
        mask = torch.zeros_like(parts.vertex_part, dtype=torch.bool)
        for s in segs:
            mask |= parts.vertex_part == s
        out.append(torch.nonzero(mask).flatten())
    return FootVertices(out[0], out[1])


def _majority(labels: Tensor, window: int = MAJORITY_WINDOW) -> Tensor:
    """``labels (F, C)`` after a centred majority vote over ``window`` frames (edges: the frames available)."""
    if labels.shape[0] == 0:
        return labels
    half = window // 2
    x = labels.float().T[:, None, :]  # (C, 1, F)
    ones = torch.ones(1, 1, window)
    counts = torch.nn.functional.conv1d(torch.nn.functional.pad(x, (half, half)), ones)[:, 0].T
    avail = torch.nn.functional.conv1d(torch.nn.functional.pad(torch.ones_like(x[:1]), (half, half)), ones)[0, 0]
    return counts > avail[:, None] / 2


def _step(p: Tensor) -> Tensor:
    """Distance ``(F,)`` each point of ``p (F, 3)`` moved since the previous frame (the first frame repeats the
    second's)."""
    out = torch.zeros(p.shape[0], dtype=p.dtype)
    if p.shape[0] > 1:
        d = (p[1:] - p[:-1]).norm(dim=-1)
        out[1:] = d
        out[0] = d[0]
    return out


def foot_joint_pairs(mapping: JointMapping) -> list[tuple[int, int]]:
    """Per side, the (toe, ankle) joint indices; the toe falls back to the ankle on rigs without toes."""
    out = []
    for side in SIDES:
        ankle = mapping.joints[f"{side}Foot"]
        out.append((mapping.joints.get(f"{side}ToeBase", ankle), ankle))
    return out


def planted_feet(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F, 2)`` bool, left and right foot planted (the module's definition)."""
    _, gpos = motion.global_transforms()
    _, rest = character.skeleton.rest_global()
    scale = character.height / REFERENCE_HEIGHT_M
    step_limit = STEP_M * scale * REFERENCE_FPS / motion.fps
    cols = []
    for toe, ankle in foot_joint_pairs(mapping):
        low = gpos[:, toe, 1] - rest[toe, 1] <= TOE_HEIGHT_M * scale
        cols.append(low & (_step(gpos[:, toe]) <= step_limit) & (_step(gpos[:, ankle]) <= step_limit))
    return _majority(torch.stack(cols, dim=1))


@dataclass
class FeetFigures:
    """The feet figures of one result against its source (lengths in cm at a 1.80 m character)."""

    foot_accuracy: float
    skate_cm: float | None
    ground_penetration_cm: float
    float_cm: float | None
    float_any_cm: float | None
    planted_frames: int

    def as_dict(self) -> dict[str, float | int | None]:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def toe_heights(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F, 2)`` how far each toe joint (left, right; the ankle without toes) stands above its rest height,
    metres at a 1.80 m character: the height :func:`planted_feet` compares with 3 cm."""
    _, gpos = motion.global_transforms()
    _, rest = character.skeleton.rest_global()
    scale = character.height / REFERENCE_HEIGHT_M
    return torch.stack([(gpos[:, toe, 1] - rest[toe, 1]) / scale for toe, _ in foot_joint_pairs(mapping)], dim=1)


def lowest_foot_heights(character: Character, mapping: JointMapping, motion: Motion) -> Tensor:
    """``(F, 2)`` height of the lowest vertex of each foot (m, on the body's own scale)."""
    grot, gpos = motion.global_transforms()
    feet = foot_vertices(character, mapping)
    return torch.stack([character.lowest_heights(v, grot, gpos) for v in feet.sides()], dim=1)


def lowest_vertex_heights(character: Character, motion: Motion, frame_chunk: int = 64) -> Tensor:
    """``(F,)`` height of the lowest vertex of the whole mesh (m)."""
    grot, gpos = motion.global_transforms()
    out = []
    for s in range(0, motion.num_frames, frame_chunk):
        out.append(character.pose_vertices(grot[s : s + frame_chunk], gpos[s : s + frame_chunk])[..., 1].amin(-1))
    return torch.cat(out) if out else torch.zeros(0)


def feet_figures(
    character: Character,
    mapping: JointMapping,
    motion: Motion,
    source_planted: Tensor,
) -> FeetFigures:
    """The feet figures of ``motion`` on ``character`` against the source's labels ``source_planted (F, 2)``
    (from :func:`planted_feet` on the source's own body)."""
    with torch.no_grad():
        to_cm = REFERENCE_HEIGHT_M / character.height * 100.0
        labels = planted_feet(character, mapping, motion)
        f = min(labels.shape[0], source_planted.shape[0])
        src = source_planted[:f]
        accuracy = float((labels[:f] == src).float().mean()) if f else 1.0
        _, gpos = motion.global_transforms()
        speeds = []
        for toe, ankle in foot_joint_pairs(mapping):
            horizontal = gpos[:f][:, [toe, ankle]][..., [0, 2]]
            speed = torch.zeros(f, 2)
            if f > 1:
                speed[1:] = (horizontal[1:] - horizontal[:-1]).norm(dim=-1) * (motion.fps / REFERENCE_FPS)
            speeds.append(speed.mean(-1))
        speed = torch.stack(speeds, dim=1)  # (F, 2)
        measured = src.clone()
        measured[0] = False  # no previous frame
        skate = float(speed[measured].mean()) * to_cm if measured.any() else None
        lowest = lowest_vertex_heights(character, motion)[:f]
        ground = float((-lowest).clamp_min(0).mean()) * to_cm if f else 0.0
        foot_low = lowest_foot_heights(character, mapping, motion)[:f]
        float_cm = float(foot_low[src].mean()) * to_cm if src.any() else None
        any_planted = src.any(-1)
        float_any = float(foot_low.amin(-1)[any_planted].mean()) * to_cm if any_planted.any() else None
    return FeetFigures(accuracy, skate, ground, float_cm, float_any, int(any_planted.sum()))


__all__ = [
    "FeetFigures",
    "FootVertices",
    "feet_figures",
    "foot_joint_pairs",
    "foot_vertices",
    "foot_vertices_of",
    "lowest_foot_heights",
    "lowest_vertex_heights",
    "planted_feet",
    "toe_heights",
]
