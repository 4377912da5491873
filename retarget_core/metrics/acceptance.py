"""The independent judge's figures (``../shared/ACCEPTANCE.md``), measured on posed meshes.

The judge reads only a result and a source (the clip on an average body). This module does the same: it
needs the two characters, their joint mappings and the two motions, nothing from the pipeline (no contact
constraints, no SDF grids), so refinement stages can be tuned against what is judged.

Conventions (ACCEPTANCE.md): every length is normalised to a 1.80 m character, each character by its own rest
mesh height; motions are resampled to 30 fps before measuring (slerp / linear, :func:`resample`), so per-frame
quantities are per 1/30 s. Parts, closed volumes, hands, feet and the seam band are in
:mod:`retarget_core.metrics.acceptance_body`.

- **Self-penetration.** A vertex of an arm is tested against torso, head, the other arm and both legs; of a leg
  against the other leg and both arms; head vertices against the torso (reported apart). Inside when the
  generalised winding number of the posed closed part is above 0.5 (libigl's fast winding number, Barill et al.
  2018: exact near field, a Taylor expansion of far clusters with beta = 2, its accuracy in docs/acceptance.md;
  exact for calls of at most ``EXACT_WN_MAX_QUERIES`` points). Depth = distance to the closed part's surface
  (exact, libigl's AABB tree). Not counted: vertices in the seam band; vertices whose closest point on the part is
  on a cap fan ("entered through a cap"). pen %v = mean over frames of the share of ALL vertices that penetrate
  (limbs only; the head apart as head %v); mean depth over penetrating (frame, vertex); frames > 1 cm = share of
  frames whose deepest counted vertex is deeper than 1 cm.
- **Hand self-contact.** Per hand and each of head, torso, the other arm, the legs (both): the distance from
  the hand's vertices to that part's closed surface (exact), 0 when a hand vertex is inside. Only hand
  vertices within ``CONTACT_RANGE_M`` of the part's bounding box are measured exactly; otherwise the distance
  recorded is the lower bound (the gap to the box), which is beyond every threshold used.
- **Feet.** Per foot: planted when the toe joint is at most 3 cm above its own rest height and moved at most
  1 cm since the last frame, and the ankle (Foot joint) moved at most 1 cm; the first frame uses the motion to
  the second; then a centred 5-frame majority (at the ends, the majority of the frames the window holds).
- **Fidelity.** End-effector error over both hands, both feet (the Foot joints) and the head, each relative to
  the Hips; jerk = mean norm of the third difference of the mapped canonical joints' world positions.

Speed: the meshes are posed by linear blend skinning in one batch; per frame and part one libigl call answers
every candidate vertex (vertices of the tested parts inside the part's posed bounding box, and hand vertices
near it). Its speed: docs/acceptance.md (``benchmarks/eval/acceptance_copy.py``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel

from retarget_core.canonical import CANONICAL_JOINTS, JointMapping
from retarget_core.character import Character
from retarget_core.metrics.acceptance_body import (
    CONTACT_PARTS,
    HANDS,
    HEAD_TESTS,
    LIMB_TESTS,
    PARTS,
    AcceptanceBody,
    ClosedPart,
    acceptance_body,
    contact_targets,
)
from retarget_core.motion import Motion
from retarget_core.resample import resample

JUDGE_FPS = 30.0
EXACT_WN_MAX_QUERIES = 4  # up to this many points: exact winding numbers in numpy beat building libigl's tree
FOOT_SIDES: tuple[str, ...] = ("left", "right")
END_EFFECTORS: tuple[str, ...] = ("LeftHand", "RightHand", "LeftFoot", "RightFoot", "Head")


@dataclass(frozen=True)
class AcceptanceParams:
    """Thresholds of ACCEPTANCE.md, lengths at a 1.80 m character, per-frame quantities at 30 fps."""

    deep_m: float = 0.01  # frames > 1 cm: deepest counted vertex deeper than this
    contact_m: float = 0.015  # a source contact: hand within 1.5 cm of the part
    kept_m: float = 0.025  # a source contact is preserved when the result's hand is within 2.5 cm
    far_m: float = 0.05  # a false contact is counted on (hand, part, frame) farther than 5 cm on the source
    false_m: float = 0.01  # ... whose result distance is below 1 cm
    contact_range_m: float = 0.06  # hand distances are exact up to at least this (above every threshold)
    toe_height_m: float = 0.03  # toe at most 3 cm above its rest height
    foot_step_m: float = 0.01  # toe and ankle moved at most 1 cm since the last frame
    foot_window: int = 5  # majority smoothing window (frames)
    frame_chunk: int = 32  # frames posed per batch (memory: chunk x V x 3 doubles)


@dataclass
class ClipAcceptance:
    """Per-frame measures of one motion on one body, lengths normalised to 1.80 m, at 30 fps.

    pen_count, pen_depth_sum, pen_max: ``(F,)`` counted limb vertices, sum and max of their depths (m).
    head_count, head_depth_sum, head_max: ``(F,)`` the same for head vertices inside the torso.
    hand_distance: ``(F, 2, 4)`` hand (left, right) x part (:data:`CONTACT_PARTS`) distance (m).
    joints: ``(F, 22, 3)`` world positions of :data:`CANONICAL_JOINTS` (NaN where not mapped).
    planted: ``(F, 2)`` feet (left, right) planted; lowest: ``(F,)`` lowest vertex height;
    lowest_foot: ``(F, 2)`` lowest vertex of each foot.
    """

    name: str
    fps: float
    height: float
    num_vertices: int
    pen_count: np.ndarray
    pen_depth_sum: np.ndarray
    pen_max: np.ndarray
    head_count: np.ndarray
    head_depth_sum: np.ndarray
    head_max: np.ndarray
    hand_distance: np.ndarray
    joints: np.ndarray
    planted: np.ndarray
    lowest: np.ndarray
    lowest_foot: np.ndarray
    duration: float
    seconds: float  # measuring time (the per-body preparation excluded)
    cpu_seconds: float  # the same in CPU time of this process (all threads): robust to a busy machine

    @property
    def num_frames(self) -> int:
        return int(self.joints.shape[0])


class AcceptanceFigures(BaseModel):
    """The judge's figures of one result against its source (lengths in cm at 1.80 m, shares in 0..1 unless
    the name says percent). None where a figure has nothing to measure (no source contact, no planted foot)."""

    frames: int
    source_frames: int
    fps: float = JUDGE_FPS
    duration_s: float
    source_duration_s: float
    pen_percent: float
    pen_mean_depth_cm: float | None
    frames_over_1cm_percent: float
    head_percent: float
    head_mean_depth_cm: float | None
    head_frames_over_1cm_percent: float
    source_contacts: int
    contact_preservation: float | None
    far_pairs: int
    false_contacts: float | None
    foot_accuracy: float | None
    source_planted_frames: int
    skate_cm: float | None
    ground_penetration_cm: float
    float_cm: float | None
    end_effector_error_cm: float
    jerk_ratio: float | None
    seconds_per_frame: float
    cpu_seconds_per_frame: float


class AcceptanceRatios(BaseModel):
    """The figures whose targets are ratios to the plain copy: after / before (None when before is 0)."""

    pen_percent: float | None
    frames_over_1cm: float | None
    end_effector_error: float | None
    head_percent: float | None


class TargetCheck(BaseModel):
    """One target of ACCEPTANCE.md: the value compared, the bound and whether it is met."""

    value: float | None
    target: str
    met: bool


# --------------------------------------------------------------------------------------------- measuring


def _posed_chunks(character: Character, motion: Motion, chunk: int):
    """Yield ``(start, posed (C, V, 3) float64 numpy)`` over the motion's frames."""
    grot, gpos = motion.global_transforms()
    with torch.no_grad():
        for s in range(0, motion.num_frames, chunk):
            e = min(motion.num_frames, s + chunk)
            yield s, character.pose_vertices(grot[s:e], gpos[s:e]).double().numpy()


def _box_gap(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance ``(N,)`` from points ``(N, 3)`` to the box ``[lo, hi]`` (0 inside)."""
    return np.linalg.norm(np.maximum(0.0, np.maximum(lo - points, points - hi)), axis=-1)


def _majority(labels: np.ndarray, window: int) -> np.ndarray:
    """``(F, C)`` bool: centred majority over ``window`` frames (the frames the window holds at the ends)."""
    f_n = labels.shape[0]
    if f_n == 0:
        return labels
    half = window // 2
    c = np.concatenate([np.zeros((1, labels.shape[1])), np.cumsum(labels, axis=0)])
    lo = np.clip(np.arange(f_n) - half, 0, f_n)
    hi = np.clip(np.arange(f_n) + half + 1, 0, f_n)
    count = c[hi] - c[lo]
    return count * 2 > (hi - lo)[:, None]


def planted_feet(joints: np.ndarray, rest_joints: np.ndarray, params: AcceptanceParams) -> np.ndarray:
    """Planted feet ``(F, 2)`` (left, right) from normalised joint positions ``(F, 22, 3)`` and the rest pose
    ``(22, 3)`` standing on y = 0 (see module doc). A rig without a toe joint (NaN) is labelled by its ankle,
    as :func:`retarget_core.metrics.feet_acceptance.foot_joint_pairs` does, not left unplanted on every frame."""
    f_n = joints.shape[0]
    raw = np.zeros((f_n, 2), dtype=bool)
    for k, side in enumerate(("Left", "Right")):
        toe, ankle = CANONICAL_JOINTS.index(f"{side}ToeBase"), CANONICAL_JOINTS.index(f"{side}Foot")
        if np.isnan(joints[:, toe]).any() or np.isnan(rest_joints[toe]).any():
            toe = ankle
        t, a = joints[:, toe], joints[:, ankle]
        if np.isnan(t).any() or np.isnan(a).any() or f_n == 0:
            continue
        moved_t, moved_a = np.zeros(f_n), np.zeros(f_n)
        if f_n > 1:
            moved_t[1:] = np.linalg.norm(t[1:] - t[:-1], axis=-1)
            moved_a[1:] = np.linalg.norm(a[1:] - a[:-1], axis=-1)
            moved_t[0], moved_a[0] = moved_t[1], moved_a[1]
        low = t[:, 1] - rest_joints[toe, 1] <= params.toe_height_m
        raw[:, k] = low & (moved_t <= params.foot_step_m) & (moved_a <= params.foot_step_m)
    return _majority(raw, params.foot_window)


def _canonical_positions(character: Character, mapping: JointMapping, gpos: torch.Tensor) -> np.ndarray:
    """``(F, 22, 3)`` world positions of the canonical joints (NaN where not mapped)."""
    out = np.full((gpos.shape[0], len(CANONICAL_JOINTS), 3), np.nan)
    for c, name in enumerate(CANONICAL_JOINTS):
        j = mapping.joints.get(name)
        if j is not None:
            out[:, c] = gpos[:, j].double().numpy()
    return out


@dataclass
class _Plan:
    """Which clusters and vertices are tested against each part (fixed per body)."""

    tester_cluster: dict[str, np.ndarray]  # part -> (C,) clusters whose part tests against it
    hand_cluster: dict[str, dict[int, np.ndarray]]  # part -> hand index -> (C,) that hand's clusters
    tester_vertex: dict[str, np.ndarray]  # part -> (V,) vertices whose part tests against it
    contact_of: list[dict[str, tuple[str, ...]]]  # per hand: contact part -> parts


def _plan(body: AcceptanceBody) -> _Plan:
    tests = {**LIMB_TESTS, **HEAD_TESTS}
    tester_cluster, hand_cluster, tester_vertex = {}, {}, {}
    contact_of = [contact_targets(h) for h in HANDS]
    for t in PARTS:
        testers = [PARTS.index(a) for a, against in tests.items() if t in against]
        tester_cluster[t] = np.isin(body.cluster_part, testers)
        tester_vertex[t] = np.isin(body.part_of_vertex, testers)
        hand_cluster[t] = {
            h: body.cluster_hand == h for h in range(len(HANDS)) if any(t in ps for ps in contact_of[h].values())
        }
    return _Plan(tester_cluster, hand_cluster, tester_vertex, contact_of)


CAP_TIE_M = 1e-7  # a closest point this close to a cap's rim lies on the part's own triangles too


def _through_cap(part: ClosedPart, local: np.ndarray, face: np.ndarray, closest: np.ndarray) -> np.ndarray:
    """``(Q,)`` the closest point ``closest (Q, 3)`` on triangle ``face (Q,)`` is on a cap fan, not on its rim
    (a point on the rim is as close to the part's own triangles: it did not enter through the cap)."""
    cap = part.is_cap[face]
    if not cap.any():
        return cap
    tri = part.faces[face[cap]]  # cap fans are (loop vertex, loop vertex, centre)
    a, b, c = local[tri[:, 0]], local[tri[:, 1]], closest[cap]
    ab = b - a
    t = np.clip(((c - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-30), 0.0, 1.0)
    on_rim = np.linalg.norm(a + ab * t[:, None] - c, axis=1) <= CAP_TIE_M
    out = cap.copy()
    out[np.nonzero(cap)[0][on_rim]] = False
    return out


def winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact generalised winding numbers ``(Q,)`` of ``points (Q, 3)`` for the triangles ``faces (T, 3)`` of
    ``vertices`` (sum of signed solid angles over 4 pi, Van Oosterom and Strackee), a ``(Q, T)`` computation."""
    a = vertices[faces[:, 0]][None] - points[:, None]
    b = vertices[faces[:, 1]][None] - points[:, None]
    c = vertices[faces[:, 2]][None] - points[:, None]
    la, lb, lc = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1), np.linalg.norm(c, axis=-1)
    det = np.einsum("qfi,qfi->qf", a, np.cross(b, c))
    dot = (
        la * lb * lc + np.einsum("qfi,qfi->qf", a, b) * lc + np.einsum("qfi,qfi->qf", b, c) * la
        + np.einsum("qfi,qfi->qf", c, a) * lb
    )  # fmt: skip
    return np.arctan2(det, dot).sum(axis=1) / (2.0 * np.pi)


def _inside(part: ClosedPart, local: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``(Q,)`` generalised winding number of the closed part above 0.5 (in absolute value): libigl's fast
    winding number (its tree is built per call, a few ms), or exactly (:func:`winding_numbers`) when there
    are at most ``EXACT_WN_MAX_QUERIES`` points."""
    import igl

    if len(q) == 0:
        return np.zeros(0, dtype=bool)
    q = np.ascontiguousarray(q)
    if len(q) > EXACT_WN_MAX_QUERIES:
        return np.abs(igl.fast_winding_number(local, part.faces, q)) > 0.5
    return np.abs(winding_numbers(local, part.faces, q)) > 0.5


@dataclass
class _Balls:
    """Bounding balls of the body's vertex clusters in one posed frame: centre ``(C, 3)``, radius ``(C,)``."""

    centre: np.ndarray
    radius: np.ndarray


def _balls(body: AcceptanceBody, p: np.ndarray) -> _Balls:
    """Each cluster's ball around its posed centroid, over the posed vertices ``p (V, 3)``."""
    members = body.cluster_members
    valid = members >= 0
    pts = p[np.where(valid, members, 0)]  # (C, K, 3)
    centre = (pts * valid[..., None]).sum(1) / valid.sum(1)[:, None]
    radius = np.sqrt(np.where(valid, ((pts - centre[:, None]) ** 2).sum(-1), 0.0).max(1))
    return _Balls(centre, radius)


@dataclass
class _PartQuery:
    """One part against one frame's balls: the posed part ``local (V, 3)``; cand ``(C,)`` the balls that may
    test against it (or hold a hand within reach), idx ``(N,)`` their indices; lower ``(C,)`` lower bounds of
    every ball's member distances to the part; d_c ``(N,)`` the candidates' centroid distances and tree the
    part's AABB tree (None without candidates)."""

    name: str
    part: ClosedPart
    local: np.ndarray
    cand: np.ndarray
    idx: np.ndarray
    lower: np.ndarray
    d_c: np.ndarray
    tree: Any


def _part_query(
    plan: _Plan, t_name: str, part: ClosedPart, p: np.ndarray, balls: _Balls, contact_range: float
) -> _PartQuery:
    """Cull the balls against part ``t_name`` posed by ``p (V, 3)``: the box gap, then the exact distance of
    each candidate's centroid to the surface (libigl AABB tree) less its radius."""
    import igl

    local = part.posed(p)
    centre, radius = balls.centre, balls.radius
    gap = _box_gap(centre, local.min(0), local.max(0))
    cand = plan.tester_cluster[t_name] & (gap <= radius)
    for hc in plan.hand_cluster[t_name].values():
        cand |= hc & (gap <= radius + contact_range)
    idx = np.nonzero(cand)[0]
    lower = gap - radius  # lower bounds of member distances (refined below for candidates)
    if not len(idx):
        return _PartQuery(t_name, part, local, cand, idx, lower, np.zeros(0), None)
    tree = igl.AABB()
    tree.init(local, part.faces)
    d2, _, _ = tree.squared_distance(local, part.faces, np.ascontiguousarray(centre[idx]))
    d_c = np.sqrt(d2)
    lower[idx] = d_c - radius[idx]
    return _PartQuery(t_name, part, local, cand, idx, lower, d_c, tree)


def _test_members(
    body: AcceptanceBody, plan: _Plan, q: _PartQuery, p: np.ndarray, balls: _Balls, depth: np.ndarray
) -> dict[int, bool]:
    """Inside tests of the candidates (members of balls that may reach the surface one by one, the centroid of
    the others); raises ``depth (V,)`` to each counted penetrating vertex's depth. Returns, per hand index,
    whether a vertex of that hand is inside the part."""
    members = body.cluster_members
    straddle = q.lower[q.idx] <= 0.0  # balls that may reach the surface: members tested one by one
    m = members[q.idx[straddle]]
    m = m[m >= 0]
    far = q.idx[~straddle]
    inside = _inside(q.part, q.local, np.concatenate([p[m], balls.centre[far]]))
    inside_m, inside_c = inside[: len(m)], inside[len(m) :]
    hand_inside = {
        h: bool((inside_c & hc[far]).any()) or bool(inside_m[body.hand_of_vertex[m] == h].any())
        for h, hc in plan.hand_cluster[q.name].items()
    }
    deep = far[inside_c & plan.tester_cluster[q.name][far]]
    if len(deep):  # whole balls inside: their members are inside too
        md = members[deep]
        md = md[md >= 0]
        m, inside_m = np.concatenate([m, md]), np.concatenate([inside_m, np.ones(len(md), dtype=bool)])
    pen = m[plan.tester_vertex[q.name][m] & inside_m & ~body.seam[m]]
    if len(pen):
        d2, face, closest = q.tree.squared_distance(q.local, q.part.faces, np.ascontiguousarray(p[pen]))
        sel = ~_through_cap(q.part, q.local, face, closest)
        np.maximum.at(depth, pen[sel], np.sqrt(d2[sel]))
    return hand_inside


def _hand_distance(
    body: AcceptanceBody, q: _PartQuery, hc: np.ndarray, p: np.ndarray, balls: _Balls, contact_range: float
) -> float:
    """The smallest distance from the hand's vertices (its clusters ``hc (C,)``) to the part, measured only on
    clusters that may hold it (exact up to ``contact_range``, beyond it a lower bound)."""
    mine = np.nonzero(hc & q.cand)[0]
    exact = math.inf
    if len(mine):
        best = float((q.d_c[np.searchsorted(q.idx, mine)] + balls.radius[mine]).min())
        near = mine[q.lower[mine] <= min(best, contact_range)]
        hv = body.cluster_members[near]
        hv = hv[hv >= 0]
        if len(hv):
            d2, _, _ = q.tree.squared_distance(q.local, q.part.faces, np.ascontiguousarray(p[hv]))
            exact = float(np.sqrt(d2.min()))
            hc = hc.copy()
            hc[near] = False
    bounds = np.maximum(q.lower[hc], 0.0)
    return min(exact, float(bounds.min()) if len(bounds) else math.inf)


def _frame(
    body: AcceptanceBody, plan: _Plan, p: np.ndarray, contact_range: float
) -> tuple[np.ndarray, dict[tuple[int, str], float]]:
    """One posed frame ``p (V, 3)``: the deepest counted penetration of every vertex ``(V,)`` (0 where none)
    and, per (hand index, part), the distance from the hand to the part (exact up to ``contact_range``,
    beyond it a lower bound).

    Culling (exact, nothing within the definitions is lost): clusters of nearby vertices are bounded by a
    ball around their posed centroid. A ball that misses the part's bounding box is outside. For the others
    the exact distance of its centroid to the surface (libigl AABB tree) less its radius bounds every
    member's distance from below; a ball that cannot reach the surface lies wholly inside or outside, so its
    centroid alone is tested; the members of the other balls are tested one by one (and those of a ball found
    wholly inside, for their depths)."""
    balls = _balls(body, p)
    depth = np.zeros(len(p))
    hand: dict[tuple[int, str], float] = {}
    for t_name in PARTS:
        part = body.part(t_name)
        if part is None:
            continue
        q = _part_query(plan, t_name, part, p, balls, contact_range)
        hand_inside = _test_members(body, plan, q, p, balls, depth) if len(q.idx) else {}
        for h, hc in plan.hand_cluster[t_name].items():
            inside = hand_inside.get(h, False)
            hand[(h, t_name)] = 0.0 if inside else _hand_distance(body, q, hc, p, balls, contact_range)
    return depth, hand


@dataclass
class PoseMeasures:
    """One posed body, on the body's own scale (m).

    depth: ``(V,)`` counted penetration depth of every vertex (0 where none; head vertices: into the torso).
    hand_distance: ``(2, 4)`` hand (left, right) x part (:data:`CONTACT_PARTS`) distance.
    """

    depth: np.ndarray
    hand_distance: np.ndarray


def measure_pose(
    character: Character, mapping: JointMapping, posed: np.ndarray, params: AcceptanceParams | None = None
) -> PoseMeasures:
    """Penetration depths and hand distances of ``character`` with posed vertices ``posed (V, 3)``."""
    params = params or AcceptanceParams()
    body = acceptance_body(character, mapping)
    plan = _plan(body)
    depth, hand = _frame(body, plan, np.asarray(posed, dtype=np.float64), params.contact_range_m / body.scale_to_180)
    return PoseMeasures(depth, _hand_table(plan, hand))


def hand_distances(
    character: Character, mapping: JointMapping, motion: Motion, params: AcceptanceParams | None = None
) -> np.ndarray:
    """``(F, 2, 4)`` the judge's hand (left, right) x part (:data:`CONTACT_PARTS`) distances (m at 1.80 m) at the
    motion's own frames (no resampling), without the penetration tests (a few ms per frame)."""
    params = params or AcceptanceParams()
    body = acceptance_body(character, mapping)
    full = _plan(body)
    none = {t: np.zeros_like(v) for t, v in full.tester_cluster.items()}
    plan = _Plan(none, full.hand_cluster, {t: np.zeros_like(v) for t, v in full.tester_vertex.items()}, full.contact_of)
    out = np.full((motion.num_frames, len(HANDS), len(CONTACT_PARTS)), np.inf)
    for start, posed in _posed_chunks(character, motion, params.frame_chunk):
        for i, p in enumerate(posed):
            out[start + i] = _hand_table(plan, _frame(body, plan, p, params.contact_range_m / body.scale_to_180)[1])
    return out * body.scale_to_180


def _hand_table(plan: _Plan, hand: dict[tuple[int, str], float]) -> np.ndarray:
    out = np.full((len(HANDS), len(CONTACT_PARTS)), np.inf)
    for h in range(len(HANDS)):
        for ci, c in enumerate(CONTACT_PARTS):
            out[h, ci] = min(hand.get((h, t), math.inf) for t in plan.contact_of[h][c])
    return out


def measure_acceptance(
    character: Character, mapping: JointMapping, motion: Motion, params: AcceptanceParams | None = None
) -> ClipAcceptance:
    """Pose ``character`` by ``motion`` (on the character's skeleton) at 30 fps and measure every frame."""
    params = params or AcceptanceParams()
    if motion.skeleton.num_joints != character.skeleton.num_joints:
        raise ValueError("the motion does not animate this character's skeleton")
    duration = motion.duration
    if abs(motion.fps - JUDGE_FPS) > 1e-6:
        motion = resample(motion, JUDGE_FPS)
    body = acceptance_body(character, mapping)  # once per body (cached): not part of the time per frame
    started, cpu_started = time.perf_counter(), time.process_time()
    plan = _plan(body)
    k = body.scale_to_180
    f_n, v_n = motion.num_frames, character.num_vertices
    contact_range = params.contact_range_m / k

    pen_count, pen_sum, pen_max = np.zeros(f_n), np.zeros(f_n), np.zeros(f_n)
    head_count, head_sum, head_max = np.zeros(f_n), np.zeros(f_n), np.zeros(f_n)
    hand_distance = np.full((f_n, len(HANDS), len(CONTACT_PARTS)), np.inf)
    lowest = np.zeros(f_n)
    lowest_foot = np.full((f_n, 2), np.nan)
    is_head = body.part_of_vertex == PARTS.index("head")

    for start, posed in _posed_chunks(character, motion, params.frame_chunk):
        lowest[start : start + len(posed)] = posed[..., 1].min(-1)
        for s, side in enumerate(FOOT_SIDES):
            fv = body.foot_vertices[side]
            if len(fv):
                lowest_foot[start : start + len(posed), s] = posed[:, fv, 1].min(-1)
        for i, p in enumerate(posed):
            f = start + i
            depth, hand = _frame(body, plan, p, contact_range)
            counted = depth > 0
            limb, head = counted & ~is_head, counted & is_head
            pen_count[f], pen_sum[f] = limb.sum(), depth[limb].sum()
            pen_max[f] = depth[limb].max() if limb.any() else 0.0
            head_count[f], head_sum[f] = head.sum(), depth[head].sum()
            head_max[f] = depth[head].max() if head.any() else 0.0
            hand_distance[f] = _hand_table(plan, hand)

    _, gpos = motion.global_transforms()
    joints = _canonical_positions(character, mapping, gpos) * k
    _, rest = character.skeleton.rest_global()
    rest_joints = _canonical_positions(character, mapping, rest[None])[0] * k
    return ClipAcceptance(
        name=motion.name,
        fps=motion.fps,
        height=body.height,
        num_vertices=v_n,
        pen_count=pen_count,
        pen_depth_sum=pen_sum * k,
        pen_max=pen_max * k,
        head_count=head_count,
        head_depth_sum=head_sum * k,
        head_max=head_max * k,
        hand_distance=hand_distance * k,
        joints=joints,
        planted=planted_feet(joints, rest_joints, params),
        lowest=lowest * k,
        lowest_foot=lowest_foot * k,
        duration=duration,
        seconds=time.perf_counter() - started,
        cpu_seconds=time.process_time() - cpu_started,
    )


# --------------------------------------------------------------------------------------------- figures


def _share(num: float, den: float) -> float:
    return float(num) / float(den) if den else 0.0


def _jerk(joints: np.ndarray) -> float | None:
    """Mean norm of the third difference ``(m per frame^3)`` over frames and mapped joints."""
    if joints.shape[0] < 4:
        return None
    j3 = joints[3:] - 3 * joints[2:-1] + 3 * joints[1:-2] - joints[:-3]
    n = np.linalg.norm(j3, axis=-1)
    n = n[~np.isnan(n)]
    return float(n.mean()) if n.size else None


def figures_from_measures(
    result: ClipAcceptance, source: ClipAcceptance, params: AcceptanceParams | None = None
) -> AcceptanceFigures:
    """The figures of ``result`` judged against ``source`` (both from :func:`measure_acceptance`)."""
    params = params or AcceptanceParams()
    cm = 100.0
    f_n = min(result.num_frames, source.num_frames)
    r_pen = result.pen_count[:f_n]
    # Penetration (the result's own).
    pen_total = float(result.pen_count.sum())
    head_total = float(result.head_count.sum())
    # Hand contacts.
    d_src, d_res = source.hand_distance[:f_n], result.hand_distance[:f_n]
    src_contact = d_src < params.contact_m
    far = d_src > params.far_m
    n_contact, n_far = int(src_contact.sum()), int(far.sum())
    preservation = float((d_res[src_contact] < params.kept_m).mean()) if n_contact else None
    false_contacts = float((d_res[far] < params.false_m).mean()) if n_far else None
    # Feet.
    planted_src = source.planted[:f_n]
    accuracy = float((result.planted[:f_n] == planted_src).mean()) if f_n else None
    skate: list[np.ndarray] = []
    for s, side in enumerate(("Left", "Right")):
        on = planted_src[1:, s]
        for name in (f"{side}ToeBase", f"{side}Foot"):
            c = CANONICAL_JOINTS.index(name)
            p = result.joints[:f_n, c]
            step = np.linalg.norm(p[1:, [0, 2]] - p[:-1, [0, 2]], axis=-1)
            skate.append(step[on & ~np.isnan(step)])
    steps = np.concatenate(skate) if skate else np.zeros(0)
    floats = result.lowest_foot[:f_n][planted_src]
    floats = floats[~np.isnan(floats)]
    # Fidelity.
    hips = CANONICAL_JOINTS.index("Hips")
    eff = [CANONICAL_JOINTS.index(n) for n in END_EFFECTORS]
    rel_r = result.joints[:f_n, eff] - result.joints[:f_n, hips : hips + 1]
    rel_s = source.joints[:f_n, eff] - source.joints[:f_n, hips : hips + 1]
    ee = np.linalg.norm(rel_r - rel_s, axis=-1)
    ee = ee[~np.isnan(ee)]
    both = ~np.isnan(result.joints[0, :, 0]) & ~np.isnan(source.joints[0, :, 0])
    jr, js = _jerk(result.joints[:f_n, both]), _jerk(source.joints[:f_n, both])
    return AcceptanceFigures(
        frames=result.num_frames,
        source_frames=source.num_frames,
        duration_s=round(result.duration, 4),
        source_duration_s=round(source.duration, 4),
        pen_percent=100.0 * float((r_pen / result.num_vertices).mean()) if f_n else 0.0,
        pen_mean_depth_cm=cm * float(result.pen_depth_sum.sum()) / pen_total if pen_total else None,
        frames_over_1cm_percent=100.0 * float((result.pen_max[:f_n] > params.deep_m).mean()) if f_n else 0.0,
        head_percent=100.0 * float((result.head_count[:f_n] / result.num_vertices).mean()) if f_n else 0.0,
        head_mean_depth_cm=cm * float(result.head_depth_sum.sum()) / head_total if head_total else None,
        head_frames_over_1cm_percent=100.0 * float((result.head_max[:f_n] > params.deep_m).mean()) if f_n else 0.0,
        source_contacts=n_contact,
        contact_preservation=preservation,
        far_pairs=n_far,
        false_contacts=false_contacts,
        foot_accuracy=accuracy,
        source_planted_frames=int(planted_src.any(-1).sum()),
        skate_cm=cm * float(steps.mean()) if steps.size else None,
        ground_penetration_cm=cm * float(np.maximum(0.0, -result.lowest[:f_n]).mean()) if f_n else 0.0,
        float_cm=cm * float(floats.mean()) if floats.size else None,
        end_effector_error_cm=cm * float(ee.mean()) if ee.size else 0.0,
        jerk_ratio=(jr / js) if (jr is not None and js) else None,
        seconds_per_frame=result.seconds / max(result.num_frames, 1),
        cpu_seconds_per_frame=result.cpu_seconds / max(result.num_frames, 1),
    )


def acceptance_figures(
    result_character: Character,
    result_mapping: JointMapping,
    result_motion: Motion,
    source_character: Character,
    source_mapping: JointMapping,
    source_motion: Motion,
    params: AcceptanceParams | None = None,
) -> AcceptanceFigures:
    """The judge's figures of a result (``result_motion`` on ``result_character``) against its source
    (``source_motion`` on ``source_character``, the clip on the source body). Measure the source once with
    :func:`measure_acceptance` and use :func:`figures_from_measures` when judging several results."""
    src = measure_acceptance(source_character, source_mapping, source_motion, params)
    res = measure_acceptance(result_character, result_mapping, result_motion, params)
    return figures_from_measures(res, src, params)


def load_judged_file(path: str | Path, clip: str | int = 0) -> tuple[Character, JointMapping, Motion]:
    """A skinned, animated glTF/GLB as the judge reads it: the file's own coordinates (metres, Y up, its floor at
    y = 0; unlike :func:`retarget_core.loading.load_motion`, which re-grounds a clip), joints mapped by name.
    Returns the character, its mapping and animation ``clip`` (index or name) on the character's skeleton."""
    from retarget_core.io.gltf_read import read_gltf
    from retarget_core.mapping import map_joints

    contents = read_gltf(path)
    if contents.character is None or not contents.motions:
        raise ValueError(f"{path}: the judge needs a skinned mesh and an animation")
    motions = contents.motions
    motion = next((m for m in motions if m.name == clip), None) if isinstance(clip, str) else motions[clip]
    if motion is None:
        raise ValueError(f"{path}: no animation named {clip!r}")
    return contents.character, map_joints(contents.character.skeleton), motion


def acceptance_figures_from_files(
    result_path: str | Path, source_path: str | Path, params: AcceptanceParams | None = None
) -> AcceptanceFigures:
    """:func:`acceptance_figures` of a result GLB against a source GLB (the clip on its source body)."""
    return acceptance_figures(*load_judged_file(result_path), *load_judged_file(source_path), params=params)


# --------------------------------------------------------------------------------------------- targets


def _ratio(after: float | None, before: float | None) -> float | None:
    if after is None or before is None or before == 0:
        return None
    return after / before


def acceptance_ratios(after: AcceptanceFigures, before: AcceptanceFigures) -> AcceptanceRatios:
    """after / before for the figures whose targets are ratios to the copy (None when before is 0)."""
    return AcceptanceRatios(
        pen_percent=_ratio(after.pen_percent, before.pen_percent),
        frames_over_1cm=_ratio(after.frames_over_1cm_percent, before.frames_over_1cm_percent),
        end_effector_error=_ratio(after.end_effector_error_cm, before.end_effector_error_cm),
        head_percent=_ratio(after.head_percent, before.head_percent),
    )


@dataclass(frozen=True)
class Targets:
    """The targets table of ACCEPTANCE.md."""

    pen_ratio: float = 0.25
    frames_over_1cm_ratio: float = 0.2
    contact_preservation: float = 0.90
    false_contacts: float = 0.02
    foot_accuracy: float = 0.97
    skate_cm: float = 0.5
    ground_penetration_cm: float = 0.5
    float_cm: tuple[float, float] = (-0.5, 1.0)
    end_effector_ratio: float = 1.3
    jerk_ratio: float = 1.1


def _ratio_check(after: float, before: float, bound: float, label: str) -> TargetCheck:
    """A ratio target; when the copy has 0 the result must have 0 too."""
    if before == 0:
        return TargetCheck(value=None, target=f"{label} (copy is 0: result must be 0)", met=after == 0)
    r = after / before
    return TargetCheck(value=r, target=label, met=r <= bound)


def meets_targets(
    after: AcceptanceFigures, before: AcceptanceFigures, targets: Targets | None = None
) -> dict[str, TargetCheck]:
    """Every target of ACCEPTANCE.md for one result (``after``) against the copy (``before``). Figures with
    nothing to measure (no source contact, no far pair, no planted foot) are met. Validity (glTF validator) is
    not checked here; the frame count and duration are (``frames``)."""
    t = targets or Targets()
    out: dict[str, TargetCheck] = {
        "pen_percent": _ratio_check(after.pen_percent, before.pen_percent, t.pen_ratio, f"<= {t.pen_ratio} x copy"),
        "frames_over_1cm": _ratio_check(
            after.frames_over_1cm_percent, before.frames_over_1cm_percent, t.frames_over_1cm_ratio,
            f"<= {t.frames_over_1cm_ratio} x copy",
        ),
        "end_effector_error": _ratio_check(
            after.end_effector_error_cm, before.end_effector_error_cm, t.end_effector_ratio,
            f"<= {t.end_effector_ratio} x copy",
        ),
    }  # fmt: skip

    def at_least(v: float | None, bound: float) -> TargetCheck:
        return TargetCheck(value=v, target=f">= {bound}", met=v is None or v >= bound)

    def at_most(v: float | None, bound: float) -> TargetCheck:
        return TargetCheck(value=v, target=f"<= {bound}", met=v is None or v <= bound)

    lo, hi = t.float_cm
    out["contact_preservation"] = at_least(after.contact_preservation, t.contact_preservation)
    out["false_contacts"] = at_most(after.false_contacts, t.false_contacts)
    out["foot_accuracy"] = at_least(after.foot_accuracy, t.foot_accuracy)
    out["skate"] = at_most(after.skate_cm, t.skate_cm)
    out["ground_penetration"] = at_most(after.ground_penetration_cm, t.ground_penetration_cm)
    out["float"] = TargetCheck(
        value=after.float_cm, target=f"in [{lo}, {hi}]", met=after.float_cm is None or lo <= after.float_cm <= hi
    )
    out["jerk_ratio"] = at_most(after.jerk_ratio, t.jerk_ratio)
    same = after.frames == after.source_frames and abs(after.duration_s - after.source_duration_s) < 1e-3
    out["frames"] = TargetCheck(value=float(after.frames), target="frames and duration equal the source's", met=same)
    return out


__all__ = [
    "JUDGE_FPS",
    "AcceptanceFigures",
    "AcceptanceParams",
    "AcceptanceRatios",
    "ClipAcceptance",
    "TargetCheck",
    "Targets",
    "acceptance_figures",
    "acceptance_figures_from_files",
    "acceptance_ratios",
    "PoseMeasures",
    "figures_from_measures",
    "load_judged_file",
    "measure_acceptance",
    "measure_pose",
    "meets_targets",
    "hand_distances",
    "planted_feet",
]
