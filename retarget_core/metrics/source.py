"""What came in broken: the source motion measured on its own body.

A capture can sink a hand into the belly, slide a planted foot, stand below the floor, hover above it, or
jitter. Retargeting copies all of that onto the target, and a reviewer comparing "before" and "after" would
blame the result. :func:`measure_source` measures the source on its body with the measures the result gets
(per-part penetration, hand depth inside the body, foot skate, ground penetration and float, jerk) and says in
words what exceeds a named threshold (:class:`SourceThresholds`). Lengths at a 1.80 m body, speeds per frame
at 30 fps (scaled to the body's height and the clip's frame rate, like the foot contact thresholds).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS, HAND_SEGMENTS, BodyParts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.energy.sdf import REFERENCE_HEIGHT_M, PartSDF
from retarget_core.metrics.compute import MetricParams, measure_clip, penetration_by_part
from retarget_core.metrics.report import SourceFlag, SourceMetrics, measure
from retarget_core.motion import Motion
from retarget_core.resample import resample

REFERENCE_FPS = 30.0
FOOT_SEGMENTS: tuple[str, ...] = ("LeftFoot", "LeftToeBase", "RightFoot", "RightToeBase")


@dataclass(frozen=True)
class SourceThresholds:
    """When a source figure becomes a warning (lengths at a 1.80 m body, per frame at 30 fps). Why each value,
    and what it flags on the shared clips: docs/metrics.md, "``source``: what came in broken"."""

    # A hand deeper than 1 cm inside another part is visibly sunk (about the most a soft belly gives under a
    # resting hand); on more than 10 % of frames it is a habit of the capture, not a graze.
    hand_depth_m: float = 0.01
    hand_frames_percent: float = 10.0
    # A planted foot (the source's own foot contacts) moving more than 1 cm a frame on average skates.
    skate_m: float = 0.01
    # A foot flat on the floor (toe and ankle within foot_down_m of their standing heights) sliding more than
    # 1 cm a frame on more than 20 % of its floor frames is a skating capture (a clean walk slides on fewer).
    foot_down_m: float = 0.03
    slide_m: float = 0.01
    slide_frames_percent: float = 20.0
    # The lowest vertex more than 1 cm below the floor on more than 10 % of frames: feet through the ground.
    ground_m: float = 0.01
    ground_frames_percent: float = 10.0
    # The lowest foot vertex more than 2 cm above the floor on average over planted frames: the body hovers
    # (about a shoe sole; the acceptance band for results is -0.5 to +1.0 cm).
    float_m: float = 0.02
    # Jitter: mean joint jerk (third difference of positions at 30 fps) above 1.5 cm/frame^3 AND out of
    # proportion to the motion, jerk / acceleration above 1.5 (white noise gives sqrt(20 / 6) = 1.83, smooth
    # motion less); either test alone overlaps clean captures.
    jerk_m: float = 0.015
    jerk_ratio: float = 1.5


def hand_vertices(parts: BodyParts) -> dict[str, Tensor]:
    """Vertex indices ``(N,)`` of each hand segment the body has (dominant segment LeftHand / RightHand)."""
    return {h: parts.part_vertices(parts.index(h)) for h in HAND_SEGMENTS if parts.find(h) is not None}


def foot_vertex_heights(body: Character, parts: BodyParts, motion: Motion, chunk: int = 64) -> Tensor:
    """``(F,)`` height of the lowest vertex of the feet (Foot, ToeBase segments; all vertices without them)."""
    segs = [parts.index(n) for n in FOOT_SEGMENTS if parts.find(n) is not None]
    if segs:
        idx = torch.nonzero(torch.isin(parts.vertex_part, torch.tensor(segs))).flatten()
    else:
        idx = torch.arange(body.num_vertices)
    grot, gpos = motion.global_transforms()
    with torch.no_grad():  # only the feet are posed
        return body.lowest_heights(idx, grot, gpos, chunk)


def _percent(mask: Tensor) -> float:
    return round(float(mask.float().mean()) * 100.0, 2) if mask.numel() else 0.0


def _feet_joint_positions(gpos: Tensor, feet: FootContacts) -> tuple[Tensor, Tensor]:
    """World positions ``(F, K, 3)`` of the rig's foot joints and the matching columns of ``feet.labels``."""
    cols = [c for c, j in enumerate(feet.joints) if 0 <= j < gpos.shape[1]]
    return gpos[:, [feet.joints[c] for c in cols]], torch.tensor(cols, dtype=torch.long)


def foot_slide(gpos: Tensor, rest_pos: Tensor, mapping: JointMapping, down: float) -> tuple[Tensor, Tensor]:
    """Per foot (left, right) and frame ``(F-1, 2)``: whether the foot is flat on the floor (toe and ankle within
    ``down`` of their standing heights at this and the previous frame) and the horizontal step of its toe and
    ankle (mean of the two, m). Feet the rig lacks give all-False columns."""
    f_n = gpos.shape[0]
    flat = torch.zeros(max(f_n - 1, 0), 2, dtype=torch.bool)
    step = torch.zeros(max(f_n - 1, 0), 2)
    if f_n < 2:
        return flat, step
    for k, side in enumerate(("Left", "Right")):
        joints = [mapping.joints.get(f"{side}{n}", -1) for n in ("ToeBase", "Foot")]
        joints = [j for j in joints if j >= 0]
        if not joints:
            continue
        p = gpos[:, joints]  # (F, n, 3)
        low = ((p[..., 1] - rest_pos[joints, 1]) <= down).all(-1)  # (F,)
        flat[:, k] = low[1:] & low[:-1]
        step[:, k] = (p[1:, :, [0, 2]] - p[:-1, :, [0, 2]]).norm(dim=-1).mean(-1)
    return flat, step


def joint_jerk(motion: Motion, mapping: JointMapping) -> tuple[float | None, float | None]:
    """Mean magnitude of the third and of the second difference of the mapped joints' positions at 30 fps
    (m/frame^3, m/frame^2)."""
    m = resample(motion, REFERENCE_FPS)
    if m.num_frames < 4:
        return None, None
    _, gpos = m.global_transforms()
    p = gpos[:, sorted(mapping.joints.values())]
    jerk = float((p[3:] - 3 * p[2:-1] + 3 * p[1:-2] - p[:-3]).norm(dim=-1).mean())
    return jerk, float((p[2:] - 2 * p[1:-1] + p[:-2]).norm(dim=-1).mean())


def measure_source(
    body: Character,
    mapping: JointMapping,
    source_view: Motion,
    sdf: PartSDF,
    feet: FootContacts,
    thresholds: SourceThresholds | None = None,
) -> tuple[SourceMetrics, list[str]]:
    """The source motion ``source_view`` (on ``body``'s skeleton) measured on ``body``: penetration by part, hand
    depth inside the body, foot skate on the planted frames of ``feet`` (the source's foot contacts) and slide
    on floor frames, ground penetration and float, jerk; and a warning for each figure over its threshold."""
    th = thresholds or SourceThresholds()
    k = REFERENCE_HEIGHT_M / body.height  # body metres -> metres at 1.80 m
    cm = 100.0
    f_n = source_view.num_frames
    per_frame = REFERENCE_FPS / source_view.fps  # a step per clip frame -> per 1/30 s is step / per_frame
    parts = sdf.parts
    measures = measure_clip(body, mapping, sdf, source_view, deep_causes=False)  # the source's deep frames' causes: unused
    depth = measures.depths  # (F, V), nonzero entries
    tol = MetricParams().penetration_tolerance_m / k
    by_part = (penetration_by_part(depth, measures.vertex_cluster, tol, measures.num_vertices)
               if measures.vertex_cluster is not None else None)  # fmt: skip
    part_means = by_part.mean(0) if by_part is not None and f_n else torch.zeros(len(CLUSTERS))
    # Hands inside the body.
    hands = hand_vertices(parts)
    hand_depth = {name: depth.frame_max(idx) if len(idx) else torch.zeros(f_n) for name, idx in hands.items()}
    hand_max = torch.stack(list(hand_depth.values()), -1).amax(-1) if hand_depth else torch.zeros(f_n)
    hand_inside = hand_max > th.hand_depth_m / k
    pen_count = max(f_n * measures.num_vertices, 1)  # body vertices x frames
    # Feet: skate on the source's planted frames, slide on floor frames.
    _, gpos = source_view.global_transforms()
    _, rest_pos = body.skeleton.rest_global()
    pos, cols = _feet_joint_positions(gpos, feet)
    skate = torch.zeros(0)
    if f_n > 1 and len(cols):
        planted = feet.labels[:f_n][:, cols]
        both = planted[1:] & planted[:-1]
        steps = (pos[1:, :, [0, 2]] - pos[:-1, :, [0, 2]]).norm(dim=-1)
        skate = steps[both] * per_frame
    flat, slide_step = foot_slide(gpos, rest_pos, mapping, th.foot_down_m / k)
    slide_step = slide_step * per_frame
    slides = slide_step[flat]
    sliding = slides > th.slide_m / k
    # Ground.
    lowest = measures.lowest_vertex
    ground_pen = (-lowest).clamp_min(0)
    below = lowest < -th.ground_m / k
    foot_low = foot_vertex_heights(body, parts, source_view)
    # Float on frames where a toe is planted (the toe label has the height test; a heel label does not, so a heel
    # resting on a bench would count as "planted" above the floor).
    toes = [c for c, n in enumerate(feet.names) if n.endswith("toe") and feet.joints[c] >= 0]
    toe_planted = feet.labels[:f_n][:, toes].any(-1) if toes else torch.zeros(f_n, dtype=torch.bool)
    float_mean = float(foot_low[toe_planted].mean()) if toe_planted.any() else None
    jerk, acc = joint_jerk(source_view, mapping)
    ratio = jerk / acc if jerk is not None and acc else None
    metrics = SourceMetrics(
        body=body.name,
        frames=f_n,
        fps=source_view.fps,
        penetrating_vertices_percent=round(float(depth.count_above(tol).sum()) * 100.0 / pen_count, 4) if f_n else None,
        penetrating_vertices_percent_by_part={n: round(float(part_means[c]), 4) for c, n in enumerate(CLUSTERS)},
        penetration_max_depth=measure(
            float(depth.frame_max().max()) * cm if f_n and depth.num_vertices else None, k, "cm"
        ),
        hand_depth_max=measure(float(hand_max.max()) * cm if f_n else None, k, "cm"),
        hand_inside_frames_percent=_percent(hand_inside),
        hand_inside_frames_percent_by_hand={h: _percent(d > th.hand_depth_m / k) for h, d in hand_depth.items()},
        foot_skate=measure(float(skate.mean()) * cm if skate.numel() else None, k, "cm/frame"),
        foot_slide_frames_percent=_percent(sliding) if slides.numel() else None,
        foot_slide=measure(float(slides.mean()) * cm if slides.numel() else None, k, "cm/frame"),
        ground_penetration_mean=measure(float(ground_pen.mean()) * cm if f_n else None, k, "cm"),
        ground_below_frames_percent=_percent(below),
        foot_float_mean=measure(float_mean * cm if float_mean is not None else None, k, "cm"),
        jerk=measure(jerk * cm if jerk is not None else None, k, "cm/frame^3"),
        jerk_to_acceleration=round(ratio, 4) if ratio is not None else None,
    )
    flags = source_flags(metrics, th)
    metrics.flags = flags
    metrics.warnings = [f.message for f in flags]
    return metrics, list(metrics.warnings)


def source_flags(m: SourceMetrics, th: SourceThresholds) -> list[SourceFlag]:
    """A :class:`SourceFlag` for every figure of ``m`` over its threshold, with a sentence for the user."""
    out: list[SourceFlag] = []
    lead = f"source (as performed by its body {m.body})"
    if m.hand_inside_frames_percent > th.hand_frames_percent:
        deep = m.hand_depth_max.value_at_180 or 0.0
        which = ", ".join(f"{h} {v:.0f} %" for h, v in m.hand_inside_frames_percent_by_hand.items() if v > 0)
        out.append(SourceFlag(
            name="hand_inside_body", value=m.hand_inside_frames_percent, threshold=th.hand_frames_percent, unit="% of frames",
            message=f"{lead}: a hand is more than {th.hand_depth_m * 100:g} cm inside the body on "
            f"{m.hand_inside_frames_percent:.0f} % of frames ({which}; deepest {deep:.1f} cm at 1.80 m; warned above "
            f"{th.hand_frames_percent:g} %). The capture sinks the hand into the body; the result inherits it.",
        ))  # fmt: skip
    skate = m.foot_skate.value_at_180
    if skate is not None and skate > th.skate_m * 100:
        out.append(SourceFlag(
            name="foot_skate", value=skate, threshold=th.skate_m * 100, unit="cm/frame at 1.80 m",
            message=f"{lead}: planted feet slide {skate:.2f} cm per frame on average (warned above "
            f"{th.skate_m * 100:g} cm per frame at 30 fps).",
        ))  # fmt: skip
    slide = m.foot_slide_frames_percent
    if slide is not None and slide > th.slide_frames_percent:
        out.append(SourceFlag(
            name="foot_slide", value=slide, threshold=th.slide_frames_percent, unit="% of floor frames",
            message=f"{lead}: feet flat on the floor slide more than {th.slide_m * 100:g} cm per frame on "
            f"{slide:.0f} % of their floor frames (mean {m.foot_slide.value_at_180:.2f} cm per frame; warned above "
            f"{th.slide_frames_percent:g} %): the capture skates.",
        ))  # fmt: skip
    if m.ground_below_frames_percent > th.ground_frames_percent:
        out.append(SourceFlag(
            name="below_floor", value=m.ground_below_frames_percent, threshold=th.ground_frames_percent, unit="% of frames",
            message=f"{lead}: the body is more than {th.ground_m * 100:g} cm below the floor on "
            f"{m.ground_below_frames_percent:.0f} % of frames (mean {m.ground_penetration_mean.value_at_180:.2f} cm "
            f"at 1.80 m; warned above {th.ground_frames_percent:g} %).",
        ))  # fmt: skip
    hover = m.foot_float_mean.value_at_180
    if hover is not None and hover > th.float_m * 100:
        out.append(SourceFlag(
            name="floats", value=hover, threshold=th.float_m * 100, unit="cm at 1.80 m",
            message=f"{lead}: planted feet hover {hover:.1f} cm above the floor on average (warned above "
            f"{th.float_m * 100:g} cm).",
        ))  # fmt: skip
    jerk, ratio = m.jerk.value_at_180, m.jerk_to_acceleration
    if jerk is not None and ratio is not None and jerk > th.jerk_m * 100 and ratio > th.jerk_ratio:
        out.append(SourceFlag(
            name="jitter", value=jerk, threshold=th.jerk_m * 100, unit="cm/frame^3 at 1.80 m, 30 fps",
            message=f"{lead}: it jitters, mean joint jerk {jerk:.2f} cm per frame^3 at 30 fps, {ratio:.2f} times its "
            f"acceleration (warned above {th.jerk_m * 100:g} and {th.jerk_ratio:g}: noise, not motion).",
        ))  # fmt: skip
    return out


__all__ = [
    "SourceThresholds",
    "foot_slide",
    "foot_vertex_heights",
    "hand_vertices",
    "joint_jerk",
    "measure_source",
    "source_flags",
]
