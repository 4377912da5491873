"""Quality metrics of a motion performed by a character (paper 1 table 1, paper 2 table 1, and what users ask for).

Two steps: :func:`measure_clip` poses the character by the motion and measures per-frame quantities once
(:class:`ClipMeasures`); :func:`summarize` turns them into the numbers of the report, comparing with the
"original" motion (the input of a refinement, normally the copy baseline) and a reference motion when given.
Lengths are reported in centimetres on the body and at a 1.80 m character (``scale_to_180 = 1.80 / height``);
see docs/metrics.md for every field.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTER_OF, CLUSTERS, END_EFFECTOR_SEGMENTS, BodyParts
from retarget_core.canonical import CANONICAL_JOINTS, JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.contacts.foot_contact import FootContactParams, FootContacts, detect_foot_contacts
from retarget_core.contacts.hand_distance import (
    HandDistanceParams,
    HandPartDistances,
    HandPartGeometry,
    hand_part_distances,
    hand_part_geometry,
)
from retarget_core.energy.sdf import (
    REFERENCE_HEIGHT_M,
    PartSDF,
    distance_matrix,
    sample_pairs,
    segment_matrices,
    vertex_depths,
)
from retarget_core.metrics.deep_frames import CAUSES, DeepFrames, deep_frames
from retarget_core.metrics.depth import VertexDepths
from retarget_core.metrics.frames import Reuse, frame_chunks, hand_part_candidates, unchanged_frames
from retarget_core.metrics.report import MethodMetrics, MetricSummary, PenetratingVertices, Series, measure
from retarget_core.motion import Motion

LIMBS: tuple[str, ...] = tuple(END_EFFECTOR_SEGMENTS)


@dataclass(frozen=True)
class MetricParams:
    """Tolerances at a 1.80 m character."""

    penetration_tolerance_m: float = 0.003
    contact_tolerance_m: float = 0.01
    frame_chunk: int = 64
    # Posed vertices x frames measured at once: 64 frames of a 13k-vertex body; fewer frames on larger bodies,
    # so the working memory stays bounded (a 53k-vertex body: 16 frames).
    chunk_vertex_frames: int = 850_000


@dataclass
class ClipMeasures:
    """Per-frame measurements of one motion on one character (SI units, on the body's own scale).

    num_vertices: body vertices (accessory meshes are not measured: their depth stays 0 and the shares are of
    body vertices; docs/meshes.md); vertex_depth still has a column per mesh vertex.

    joints: ``(F, C, 3)`` world positions of the mapped canonical joints (``joint_names``).
    depths: the weighted penetration depth of every vertex per frame, ``(F, V)`` (m), as its nonzero entries
        (:class:`VertexDepths`; ``vertex_depth`` gives the dense array).
    penetration_volume: ``(F,)`` sum of vertex area x depth (m^3).
    limb_distance: ``(F, 4)`` paper 2's signed distance of each limb's end segments to the nearest segment of
        another cluster (m, capped at the grid margin), limbs in :data:`LIMBS` order.
    lowest_vertex: ``(F,)`` height of the lowest body vertex (m).
    contact_distance: ``(M,)`` distance of each contact constraint's vertex pair (m); contact_frame ``(M,)``.
    feet: foot contacts detected on this motion.
    vertex_cluster: ``(V,)`` index into :data:`CLUSTERS` of each vertex's part (its dominant segment's
        cluster), for the per-part penetration split; None when not known.
    contact_hands: per source contact (frame, hand, touched part), the hand's distance to that part here.
    """

    name: str
    fps: float
    height: float
    num_vertices: int
    joint_names: list[str]
    joints: Tensor
    depths: VertexDepths
    penetration_volume: Tensor
    limb_distance: Tensor
    lowest_vertex: Tensor
    contact_distance: Tensor
    contact_frame: Tensor
    feet: FootContacts
    vertex_cluster: Tensor | None = None
    # Hand-to-part distance of every source contact (see :func:`measure_contact_hands`).
    contact_hands: ContactHandMeasures | None = None
    deep: DeepFrames | None = None  # why each frame deeper than 1 cm is (:mod:`retarget_core.metrics.deep_frames`)

    @property
    def num_frames(self) -> int:
        return int(self.joints.shape[0])

    @property
    def scale_to_180(self) -> float:
        return REFERENCE_HEIGHT_M / self.height

    @property
    def vertex_depth(self) -> Tensor:
        """The dense ``(F, V)`` depths (scripts and tests; F x V floats)."""
        return self.depths.dense()


def limb_distances(parts: BodyParts, dist: Tensor) -> Tensor:
    """``(F, 4)`` from paper 2's M_dist ``(F, S, S)``: per limb, the minimum over its end segments (hand and
    forearm; foot, toe and shin) against every segment of another cluster, with paper 2's mask Omega."""
    mask = parts.collision_mask(ignore_arm_chest=True)
    out = []
    big = torch.finfo(dist.dtype).max
    for limb in LIMBS:
        rows = [parts.index(n) for n in END_EFFECTOR_SEGMENTS[limb] if parts.find(n) is not None]
        if not rows:
            out.append(torch.full(dist.shape[:1], float("nan"), dtype=dist.dtype))
            continue
        sub = torch.where(mask[rows][None], dist[:, rows], torch.full_like(dist[:, rows], big))
        out.append(sub.amin(dim=(1, 2)))
    return torch.stack(out, dim=1)


def measure_clip(
    character: Character,
    mapping: JointMapping,
    sdf: PartSDF,
    motion: Motion,
    contacts: ContactConstraints | None = None,
    ground: float = 0.0,
    params: MetricParams | None = None,
    foot_params: FootContactParams | None = None,
    source_hand_distances: HandPartDistances | None = None,
    reuse: Reuse | None = None,
    cull_hands: bool = True,
    deep_causes: bool = True,
) -> ClipMeasures:
    """Pose ``character`` by ``motion`` (its skeleton must be the character's) and measure every frame.
    ``source_hand_distances``: the source's hand-to-part distances (``SelfContacts.distances``), for the false
    contacts (docs/metrics.md "Hand contacts"). ``reuse``: measures of another motion on this character (same
    ground, contacts and source): frames posed exactly as there are copied, not measured. ``cull_hands``: compute
    exact hand-to-part distances only where the penetration queries found a hand near a part (False: on every
    frame, the reference the culled path is tested against). ``deep_causes``: read why each frame deeper than 1 cm
    is (:mod:`retarget_core.metrics.deep_frames`; else only which are)."""
    params = params or MetricParams()
    if motion.skeleton.num_joints != character.skeleton.num_joints:
        raise ValueError("the motion does not animate this character's skeleton")
    parts = sdf.parts
    f_n, v_n = motion.num_frames, character.num_vertices
    names = [c for c in CANONICAL_JOINTS if c in mapping.joints]
    idx = torch.tensor([mapping.joints[c] for c in names])
    out = _FrameMeasures(f_n, v_n, parts.body)
    hands = None
    if (contacts is not None and contacts.count) or source_hand_distances is not None:
        hands = ContactHandMeter(character, parts, contacts, source_hand_distances, f_n)
    same = unchanged_frames(motion, reuse.motion if reuse is not None else None)
    with torch.no_grad():
        grot, gpos = motion.global_transforms()
        if reuse is not None and bool(same.any()):
            out.copy(torch.nonzero(same).flatten(), reuse.measures, ground, hands)  # type: ignore[arg-type]
        posed_n = parts.body_count
        chunk = max(1, min(params.frame_chunk, params.chunk_vertex_frames // max(posed_n, 1)))
        for frames in frame_chunks(torch.nonzero(~same).flatten(), chunk):
            out.measure(character, sdf, grot[frames], gpos[frames], frames, hands, cull_hands)
        _, rest_pos = character.skeleton.rest_global()
        feet = detect_foot_contacts(gpos, rest_pos, mapping, character.height, motion.fps, ground, foot_params)
        c_dist, c_frame = contact_pair_distances(character, contacts, grot, gpos, params.frame_chunk)
    depths = VertexDepths.concat(out.depth, f_n, v_n)
    scale = REFERENCE_HEIGHT_M / character.height
    deep = deep_frames(character, sdf, depths, grot, gpos, mapping.joints, scale, deep_causes)
    return ClipMeasures(
        motion.name, motion.fps, character.height, parts.body_count, names, gpos[:, idx], depths, out.volume,
        out.limb, out.lowest - ground, c_dist, c_frame, feet, vertex_part_clusters(parts),
        hands.result() if hands is not None else None, deep,
    )  # fmt: skip


class _FrameMeasures:
    """The per-frame arrays of :class:`ClipMeasures`, filled chunk by chunk of frames."""

    def __init__(self, f_n: int, v_n: int, body: Tensor | None) -> None:
        self.f_n = f_n
        self.depth: list[VertexDepths] = []  # per chunk
        self.body = None if body is None else torch.nonzero(body).flatten()  # only these are posed and measured
        self.volume = torch.zeros(f_n)
        self.limb = torch.zeros(f_n, len(LIMBS))
        self.lowest = torch.zeros(f_n)

    def measure(self, character: Character, sdf: PartSDF, grot: Tensor, gpos: Tensor, frames: Tensor,
                hands: ContactHandMeter | None, cull_hands: bool) -> None:  # fmt: skip
        """Pose and measure the frames ``frames (C,)`` whose world transforms are ``grot (C, J, 4)``, ``gpos``."""
        c = len(frames)
        mats = segment_matrices(character, sdf.parts, grot, gpos)
        if self.body is None:
            verts = character.pose_vertices(grot, gpos)
            samples = sample_pairs(sdf, verts, mats)
        else:  # accessory meshes: the body vertices only
            verts = character.pose_vertex_subset(self.body, grot, gpos)
            samples = sample_pairs(sdf, verts, mats, vertices=self.body)
        d = vertex_depths(sdf, samples, c)
        self.depth.append(VertexDepths.from_dense(d, frames, self.f_n))
        self.volume[frames] = (d * sdf.vertex_area).sum(-1)
        self.limb[frames] = limb_distances(sdf.parts, distance_matrix(sdf, samples, c))
        self.lowest[frames] = verts[..., 1].amin(-1)
        if hands is not None:
            cand = hand_part_candidates(sdf.parts, samples, c) if cull_hands else None
            hands.measure(self._full(verts, character.num_vertices), frames, cand)

    def _full(self, verts: Tensor, v_n: int) -> Tensor:
        """Posed body vertices as ``(C, V, 3)`` in mesh order (accessory rows 0: no query reads them)."""
        if self.body is None:
            return verts
        return verts.new_zeros(verts.shape[0], v_n, 3).index_copy_(1, self.body, verts)

    def copy(self, frames: Tensor, other: ClipMeasures, ground: float, hands: ContactHandMeter | None) -> None:
        """Copy the frames ``frames (C,)`` from ``other`` (a motion posed the same there, measured with the same
        ``ground``)."""
        self.depth.append(other.depths.select_frames(frames))
        self.volume[frames] = other.penetration_volume[frames]
        self.limb[frames] = other.limb_distance[frames]
        self.lowest[frames] = other.lowest_vertex[frames] + ground
        if hands is not None:
            if other.contact_hands is None:
                raise ValueError("the reused measures have no hand-to-part distances")
            hands.copy(frames, other.contact_hands)


def contact_pair_distances(character: Character, contacts: ContactConstraints | None, grot: Tensor, gpos: Tensor,
                           chunk: int) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Distance ``(M,)`` of each contact constraint's vertex pair and its frame ``(M,)``, ordered by chunk of
    ``chunk`` frames (the order of the per-chunk measures before)."""
    if contacts is None or not contacts.count:
        return torch.zeros(0), torch.zeros(0, dtype=torch.long)
    order = torch.argsort(torch.div(contacts.frame, chunk, rounding_mode="floor"), stable=True)
    frame, i, j = contacts.frame[order], contacts.i[order], contacts.j[order]
    used, inv = torch.unique(torch.cat([i, j]), return_inverse=True)
    pts = character.pose_vertex_subset(used, grot, gpos)  # (F, U, 3)
    flat = pts.reshape(-1, 3)
    a = flat.index_select(0, frame * len(used) + inv[: len(i)])
    b = flat.index_select(0, frame * len(used) + inv[len(i) :])
    return (a - b).norm(dim=-1), frame


# --- penetration per body part -------------------------------------------------------------------------------


def vertex_part_clusters(parts: BodyParts) -> Tensor:
    """``(V,)`` index into :data:`CLUSTERS` of every vertex (the cluster of its dominant segment)."""
    return torch.tensor(parts.cluster, dtype=torch.long).index_select(0, parts.vertex_part)


def penetration_by_part(depths: VertexDepths, vertex_cluster: Tensor, tolerance: float,
                        count: int | None = None) -> Tensor:  # fmt: skip
    """``(F, 6)`` per frame and part (:data:`CLUSTERS` order): the share (%) of ALL body vertices (``count``,
    default all columns) that belong to that part and are deeper than ``tolerance`` (m), so the six columns add up
    to the frame's penetrating share."""
    f_n = depths.num_frames
    v_n = depths.num_vertices if count is None else count
    if v_n == 0:
        return torch.zeros(f_n, len(CLUSTERS))
    return depths.count_above(tolerance, vertex_cluster, len(CLUSTERS)).float() * (100.0 / v_n)


def part_split(m: ClipMeasures, tolerance: float) -> tuple[dict[str, float] | None, dict[str, Series]]:
    """The summary ``penetrating_vertices_percent_by_part`` (mean over frames per part) and its per-frame
    series ``penetrating_vertices_percent_<part>``; ``(None, {})`` when the vertices' parts are not known."""
    if m.vertex_cluster is None:
        return None, {}
    per_frame = penetration_by_part(m.depths, m.vertex_cluster, tolerance, m.num_vertices)
    means = per_frame.mean(0) if m.num_frames else torch.zeros(len(CLUSTERS))
    summary = {name: round(float(means[c]), 4) for c, name in enumerate(CLUSTERS)}
    series = {f"penetrating_vertices_percent_{name}": _series(per_frame[:, c], "%") for c, name in enumerate(CLUSTERS)}
    return summary, series


# --- hand-to-part distances of the source contacts on this body -----------------------------------------------
# ACCEPTANCE.md "contact preservation": a source contact (hand, part, frame) is kept when the result's hand is
# within 2.5 cm (at 1.80 m) of that part's surface, 0 when inside. Vertex pairs (contact_distance above) carry the
# correspondence's error (docs/metrics.md), larger than their 1 cm threshold.

CONTACT_KEPT_M = 0.025  # at 1.80 m: ACCEPTANCE.md "contact preservation"
FALSE_CONTACT_M = 0.01  # at 1.80 m: ACCEPTANCE.md "false contacts" (far on the source, closer than this here)


@dataclass
class ContactHandMeasures:
    """Per source contact ``(N,)``: frame, hand (index into ``hands``), touched part (index into ``parts``), and
    the hand's distance to that part's surface on this body (m, 0 inside, ``max_distance`` where farther).
    far_pairs: (hand, part, frame) farther than 5 cm (at 1.80 m) apart on the source, when the source's
    distances were given (else None); false_pairs: how many of them are closer than 1 cm here."""

    hands: tuple[str, ...]
    parts: tuple[str, ...]
    frame: Tensor
    hand: Tensor
    part: Tensor
    distance: Tensor
    max_distance: float
    far_pairs: int | None = None
    false_pairs: int = 0
    frame_far: Tensor | None = None  # (F,) far pairs per frame
    frame_false: Tensor | None = None  # (F,) false contacts per frame


def contact_hand_targets(contacts: ContactConstraints, hands: tuple[str, ...]) -> tuple[Tensor, Tensor, Tensor]:
    """The distinct source contacts ``(frame, hand, part)`` ``(N,)`` of ``contacts`` (hand indices into ``hands``,
    parts into CLUSTERS; without ``contacts.part``, the cluster of the pair's other segment)."""
    names = contacts.part_names
    none = torch.zeros(0, dtype=torch.long)
    if not contacts.count or int(contacts.hand.max()) >= len(names) or int(contacts.other.max()) >= len(names):
        return none, none, none  # constraints without part names: nothing to say which hand touched what
    hand_of = torch.tensor([hands.index(n) if n in hands else -1 for n in names], dtype=torch.long)
    if contacts.part is not None:
        part = contacts.part
    else:
        part_of = torch.tensor([CLUSTERS.index(CLUSTER_OF[n]) for n in names], dtype=torch.long)
        part = part_of[contacts.other]
    hand = hand_of[contacts.hand]
    ok = hand >= 0
    key = torch.stack([contacts.frame[ok], hand[ok], part[ok]], dim=1)
    key = torch.unique(key, dim=0) if len(key) else key.reshape(0, 3)
    return key[:, 0], key[:, 1], key[:, 2]


_HAND_GEOMETRY: OrderedDict[tuple[int, int], tuple[Character, BodyParts, HandPartGeometry]] = OrderedDict()
_HAND_GEOMETRY_KEPT = 4  # bodies whose hand geometry stays in memory


def cached_hand_geometry(character: Character, parts: BodyParts) -> HandPartGeometry:
    """:func:`hand_part_geometry` of ``character`` cut into ``parts``, built once per (character, parts) object
    pair: "before" and "after" of a job share it."""
    key = (id(character), id(parts))
    hit = _HAND_GEOMETRY.get(key)
    if hit is not None and hit[0] is character and hit[1] is parts:
        _HAND_GEOMETRY.move_to_end(key)
        return hit[2]
    geometry = hand_part_geometry(parts, character.vertices, character.height)
    _HAND_GEOMETRY[key] = (character, parts, geometry)
    while len(_HAND_GEOMETRY) > _HAND_GEOMETRY_KEPT:
        _HAND_GEOMETRY.popitem(last=False)
    return geometry


class ContactHandMeter:
    """Measures, chunk by chunk of posed frames, the hand-to-part distance of each source contact, and per frame
    the source's far (hand, part) pairs and how many of them are false contacts here."""

    def __init__(self, character: Character, parts: BodyParts, contacts: ContactConstraints | None,
                 source: HandPartDistances | None = None, frames: int = 0) -> None:  # fmt: skip
        self.geometry = cached_hand_geometry(character, parts)
        self.character, self.parts = character, parts
        if contacts is not None and contacts.count:
            self.frame, self.hand, self.part = contact_hand_targets(contacts, self.geometry.hands)
        else:
            self.frame = self.hand = self.part = torch.zeros(0, dtype=torch.long)
        self.distance = torch.full((len(self.frame),), float("inf"))
        self.max_distance = HandDistanceParams().max_distance_m * character.height / REFERENCE_HEIGHT_M
        self.source = source if source is not None and source.num_frames >= frames else None
        self.frame_far = torch.zeros(frames, dtype=torch.long)
        self.frame_false = torch.zeros(frames, dtype=torch.long)
        self.false_m = FALSE_CONTACT_M * character.height / REFERENCE_HEIGHT_M

    def measure(self, verts: Tensor, frames: Tensor, candidates: Tensor | None = None) -> None:
        """``verts (C, V, 3)``: the posed frames ``frames (C,)`` (increasing). ``candidates (C, 2, P)``: the
        (hand, part) pairs that may be closer than the false-contact distance (:func:`hand_part_candidates`);
        None: every far pair is measured exactly."""
        sel = torch.isin(self.frame, frames)
        row = torch.searchsorted(frames, self.frame[sel])
        need = torch.zeros(len(frames), *self.geometry.measured.shape, dtype=torch.bool)
        need[row, self.hand[sel], self.part[sel]] = True  # the source contacts' pairs
        far = None
        far_only = torch.zeros_like(need)
        if self.source is not None:
            far = torch.isinf(self.source.distance[frames]) & self.source.measured[None] & self.geometry.measured[None]
            self.frame_far[frames] = far.flatten(1).sum(1)
            far_only = (far if candidates is None else far & candidates) & ~need
        dist = self._distances(verts, need, far_only)
        if far is not None:
            self.frame_false[frames] = (far & (dist < self.false_m)).flatten(1).sum(1)
        self.distance[sel] = dist[row, self.hand[sel], self.part[sel]].float()

    def _distances(self, verts: Tensor, need: Tensor, far_only: Tensor) -> Tensor:
        """Hand-to-part distances ``(C, 2, P)`` of the pairs ``need (C, 2, P)`` up to the full reach and of the
        pairs ``far_only`` up to the false-contact distance (all a false contact asks; nearer frames are culled
        sooner), inf elsewhere: one query over the frames that need either."""
        dist = torch.full(need.shape, float("inf"), dtype=torch.float64)
        rows = torch.nonzero((need | far_only).flatten(1).any(1)).flatten()
        if len(rows):
            cutoffs = torch.where(need, self.max_distance, torch.where(far_only, self.false_m, 0.0))
            found = hand_part_distances(self.character, self.parts, verts[rows], geometry=self.geometry,
                                        cutoffs=cutoffs[rows])  # fmt: skip
            dist[rows] = found.distance
        return dist

    def copy(self, frames: Tensor, other: ContactHandMeasures) -> None:
        """Take the results of ``frames (C,)`` from ``other``, measured on a motion posed the same there."""
        sel = torch.isin(self.frame, frames)
        same = torch.isin(other.frame, frames)
        if int(sel.sum()) != int(same.sum()):
            raise ValueError("the reused measures have other source contacts on the unchanged frames")
        self.distance[sel] = other.distance[same]
        if other.frame_far is not None and other.frame_false is not None:
            self.frame_far[frames] = other.frame_far[frames]
            self.frame_false[frames] = other.frame_false[frames]

    def result(self) -> ContactHandMeasures:
        g = self.geometry
        dist = self.distance.clamp_max(self.max_distance)
        if self.source is None:
            return ContactHandMeasures(g.hands, g.parts, self.frame, self.hand, self.part, dist, self.max_distance)
        return ContactHandMeasures(g.hands, g.parts, self.frame, self.hand, self.part, dist, self.max_distance,
                                   int(self.frame_far.sum()), int(self.frame_false.sum()), self.frame_far,
                                   self.frame_false)  # fmt: skip


def contact_hand_summary(m: ClipMeasures) -> dict[str, Any]:
    """The summary fields of the source contacts' hand distances (docs/metrics.md "Hand contacts")."""
    s = m.scale_to_180
    c = m.contact_hands
    false = None
    if c is not None and c.far_pairs:
        false = _round(c.false_pairs / c.far_pairs)
    if c is None or len(c.frame) == 0:
        return {"hand_contacts": 0, "contact_preservation": None,
                "contact_hand_distance_mean": measure(None, s, "cm"), "false_contacts": false}  # fmt: skip
    kept = c.distance < CONTACT_KEPT_M / s
    return {
        "hand_contacts": int(len(c.frame)),
        "contact_preservation": _round(float(kept.float().mean())),
        "contact_hand_distance_mean": measure(float(c.distance.mean()) * 100.0, s, "cm"),
        "false_contacts": false,
    }


def contact_hand_series(m: ClipMeasures) -> dict[str, Series]:
    """Per frame, the largest hand-to-part distance of the frame's source contacts (cm at 1.80 m)."""
    c = m.contact_hands
    if c is None or len(c.frame) == 0:
        return {}
    worst = torch.zeros(m.num_frames).scatter_reduce(0, c.frame, c.distance, "amax", include_self=False)
    has = torch.zeros(m.num_frames, dtype=torch.bool)
    has[c.frame] = True
    return {"contact_hand_distance": _series(worst * m.scale_to_180 * 100.0, "cm at 1.80 m", has)}


# --- end of hand-to-part contact distances ------------------------------------------------------------------


def _mean(x: Tensor) -> float | None:
    return float(x.mean()) if x.numel() else None


def _round(x: float | None, digits: int = 4) -> float | None:
    return None if x is None else round(x, digits)


def _scaled(x: float | None, factor: float) -> float | None:
    return None if x is None else x * factor


def _series(values: Tensor, unit: str, valid: Tensor | None = None, digits: int = 4) -> Series:
    vals = [round(float(v), digits) for v in values.tolist()]
    out: list[float | None] = list(vals)
    if valid is not None:
        out = [v if ok else None for v, ok in zip(vals, valid.tolist(), strict=True)]
    return Series(unit=unit, values=out)


def _joint_errors(a: ClipMeasures, b: ClipMeasures, root_relative: bool) -> Tensor:
    """Per frame mean joint distance ``(F,)`` (m) over the canonical joints both clips have."""
    common = [n for n in a.joint_names if n in b.joint_names]
    ia = torch.tensor([a.joint_names.index(n) for n in common])
    ib = torch.tensor([b.joint_names.index(n) for n in common])
    pa, pb = a.joints[:, ia], b.joints[:, ib]
    if root_relative and "Hips" in common:
        h = common.index("Hips")
        pa, pb = pa - pa[:, h : h + 1], pb - pb[:, h : h + 1]
    f = min(pa.shape[0], pb.shape[0])
    return (pa[:f] - pb[:f]).norm(dim=-1).mean(-1)


@dataclass
class _Penetration:
    """Per frame ``(F,)``: the deepest vertex (m), the share (%) of body vertices deeper than the tolerance, the
    lowest vertex's depth below the ground (m); the per-part split (:func:`part_split`)."""

    frame_max: Tensor
    vertices: Tensor
    ground: Tensor
    by_part: dict[str, float] | None
    part_series: dict[str, Series]


def _penetration(m: ClipMeasures, tol: float) -> _Penetration:
    """Penetration of ``m``'s vertices deeper than ``tol`` (m, the body's scale) and of the ground."""
    share = m.depths.count_above(tol).float() * (100.0 / max(m.num_vertices, 1))
    return _Penetration(m.depths.frame_max(), share, (-m.lowest_vertex).clamp_min(0), *part_split(m, tol))


@dataclass
class _Collisions:
    """Paper 2's collision figures (m^2): m_c over colliding limbs, m_i and m_o over the limbs that collided in
    the original; depth ``(F,)`` the deepest limb's collision depth (m)."""

    m_c: float | None
    m_i: float | None
    m_o: float | None
    depth: Tensor


def _collisions(m: ClipMeasures, original: ClipMeasures | None) -> _Collisions:
    """Collision figures of ``m``'s limb distances ``(F, 4)`` against ``original``'s (``m``'s own without it)."""
    d_cur = m.limb_distance
    d_org = (original or m).limb_distance[: m.num_frames]
    valid = ~torch.isnan(d_cur)
    colliding = (d_cur < 0) & valid
    m_c = _mean(d_cur[colliding].pow(2)) if colliding.any() else 0.0
    was = (d_org < 0) & valid[: d_org.shape[0]]
    cur_at = d_cur[: d_org.shape[0]][was]
    m_i = _mean(cur_at.clamp_max(0).pow(2)) if was.any() else None
    m_o = _mean(cur_at.clamp_min(0).pow(2)) if was.any() else None
    return _Collisions(m_c, m_i, m_o, (-d_cur).clamp_min(0).nan_to_num(0.0).amax(-1))


@dataclass
class _Contacts:
    """Contact pair figures (m): mean, mean square, share within tolerance (%); per frame ``(F,)`` the pairs'
    count and mean distance."""

    mean: float | None
    mse: float | None
    satisfied: float | None
    count: Tensor
    per_frame: Tensor


def _contacts(m: ClipMeasures, params: MetricParams) -> _Contacts:
    """Figures of the contact constraints' vertex-pair distances ``(M,)``."""
    s = m.scale_to_180
    c_count = torch.zeros(m.num_frames).index_add(0, m.contact_frame, torch.ones_like(m.contact_distance))
    c_sum = torch.zeros(m.num_frames).index_add(0, m.contact_frame, m.contact_distance)
    return _Contacts(
        _mean(m.contact_distance), _mean(m.contact_distance.pow(2)),
        _mean((m.contact_distance < params.contact_tolerance_m / s).float() * 100.0), c_count,
        c_sum / c_count.clamp_min(1),
    )  # fmt: skip


@dataclass
class _Feet:
    """Foot figures: accuracy against the source's labels (None without them); planted ``(F, 4')`` the labels
    skate is measured on; skate ``(N,)`` horizontal steps of planted feet (m/frame), per frame ``(F,)`` their
    mean and whether the frame has one."""

    accuracy: float | None
    planted: Tensor
    skate: Tensor
    skate_frame: Tensor
    skate_valid: Tensor


def _feet(m: ClipMeasures, source_feet: FootContacts | None) -> _Feet:
    """Foot contact accuracy and skate of ``m``, on the source's planted frames when given, else its own."""
    f_n = m.num_frames
    avail = m.feet.available
    labels = m.feet.labels[:, avail]
    accuracy = None
    if source_feet is not None and avail.any():
        src = source_feet.labels[:f_n][:, avail]
        accuracy = float((labels[: src.shape[0]] == src).float().mean())
    planted = source_feet.labels[:f_n][:, avail] if source_feet is not None else labels
    joints_feet = torch.tensor([j for j in m.feet.joints if j >= 0])
    skate_frame = torch.zeros(f_n)
    skate_valid = torch.zeros(f_n, dtype=torch.bool)
    skate_all: list[Tensor] = []
    if f_n > 1 and len(joints_feet):
        feet_idx = [m.joint_names.index(n) for n in _foot_names(m.feet) if n in m.joint_names]
        pos = m.joints[:, feet_idx]
        step = (pos[1:, :, [0, 2]] - pos[:-1, :, [0, 2]]).norm(dim=-1)  # (F-1, 4)
        both = planted[1:] & planted[:-1]
        skate_all.append(step[both])
        cnt = both.sum(-1)
        skate_frame[1:] = (step * both).sum(-1) / cnt.clamp_min(1)
        skate_valid[1:] = cnt > 0
    skate = torch.cat(skate_all) if skate_all else torch.zeros(0)
    return _Feet(accuracy, planted, skate, skate_frame, skate_valid)


def _global_position_mse(m: ClipMeasures, reference: ClipMeasures) -> float:
    """Mean squared joint position error (m^2) against ``reference`` over the canonical joints both have."""
    common = [n for n in m.joint_names if n in reference.joint_names]
    ia = torch.tensor([m.joint_names.index(n) for n in common])
    ib = torch.tensor([reference.joint_names.index(n) for n in common])
    f = min(m.num_frames, reference.num_frames)
    return float((m.joints[:f, ia] - reference.joints[:f, ib]).pow(2).sum(-1).mean())


@dataclass
class _Errors:
    """Per frame ``(F,)`` MPJPE against the original and global position error against the reference (m), and
    the global position MSE (m^2); None where there is nothing to compare with."""

    mpjpe: Tensor | None
    gpe: Tensor | None
    gpe_mse: float | None


def _errors(m: ClipMeasures, original: ClipMeasures | None, reference: ClipMeasures | None) -> _Errors:
    """MPJPE (root-relative, against ``original``) and global position error (against ``reference``)."""
    return _Errors(
        _joint_errors(m, original, True) if original is not None else None,
        _joint_errors(m, reference, False) if reference is not None else None,
        _global_position_mse(m, reference) if reference is not None else None,
    )


def _summary(
    m: ClipMeasures, tol: float, pen: _Penetration, col: _Collisions, con: _Contacts, feet: _Feet, err: _Errors
) -> MetricSummary:
    """The summary numbers, in cm (and cm^2, cm^3) on the body with their values at 1.80 m."""
    s, cm, f_n = m.scale_to_180, 100.0, m.num_frames
    frame_max, ground_pen = pen.frame_max, pen.ground
    acc, jerk = _smoothness(m.joints)
    return MetricSummary(
        frames=f_n,
        fps=m.fps,
        penetration_volume=measure(float(m.penetration_volume.mean()) * cm**3 if f_n else None, s**3, "cm^3"),
        penetration_max_depth=measure(float(frame_max.max()) * cm if f_n else None, s, "cm"),
        penetration_mean_depth=measure(float(frame_max.mean()) * cm if f_n else None, s, "cm"),
        penetrating_vertices_percent=_round(_mean(pen.vertices)),
        penetrating_frames_percent=_round(_mean((frame_max > tol).float() * 100.0)),
        penetrating_vertices_percent_by_part=pen.by_part,
        deep_frames_percent=m.deep.percent() if m.deep is not None else None,
        deep_frames_percent_by_cause=m.deep.percent_by_cause() if m.deep is not None else None,
        contact_pairs=int(m.contact_distance.numel()),
        contact_frames=int((con.count > 0).sum()),
        contact_distance_mean=measure(con.mean * cm if con.mean is not None else None, s, "cm"),
        contact_mse=measure(con.mse * cm**2 if con.mse is not None else None, s**2, "cm^2"),
        contact_satisfied_percent=_round(con.satisfied),
        foot_contact_accuracy=_round(feet.accuracy),
        foot_skate=measure(float(feet.skate.mean()) * cm if feet.skate.numel() else None, s, "cm/frame"),
        foot_contact_frames=int(feet.planted.any(-1).sum()) if feet.planted.numel() else 0,
        ground_penetration_mean=measure(float(ground_pen.mean()) * cm if f_n else None, s, "cm"),
        ground_penetration_max=measure(float(ground_pen.max()) * cm if f_n else None, s, "cm"),
        global_position_error=measure(_scaled(_mean(err.gpe) if err.gpe is not None else None, cm), s, "cm"),
        global_position_mse=measure(err.gpe_mse * cm**2 if err.gpe_mse is not None else None, s**2, "cm^2"),
        mpjpe=measure(_scaled(_mean(err.mpjpe) if err.mpjpe is not None else None, cm), s, "cm"),
        m_c=measure(col.m_c * cm**2 if col.m_c is not None else None, s**2, "cm^2"),
        m_i=measure(col.m_i * cm**2 if col.m_i is not None else None, s**2, "cm^2"),
        m_o=measure(col.m_o * cm**2 if col.m_o is not None else None, s**2, "cm^2"),
        acceleration=measure(acc * cm if acc is not None else None, s, "cm/frame^2"),
        jerk=measure(jerk * cm if jerk is not None else None, s, "cm/frame^3"),
        **contact_hand_summary(m),
    )


DEEP_CAUSE_UNIT = ", ".join(f"{i} {c}" for i, c in enumerate(CAUSES))  # the deep_frame_cause series' codes


def _all_series(
    m: ClipMeasures, k: float, pen: _Penetration, col: _Collisions, con: _Contacts, feet: _Feet, err: _Errors
) -> dict[str, Series]:
    """The per-frame series, in cm at 1.80 m (``k``: cm at 1.80 m per body metre; also cm^3, %, 0/1)."""
    series: dict[str, Series] = {
        "penetration_max_depth": _series(pen.frame_max * k, "cm at 1.80 m"),
        "penetration_volume": _series(m.penetration_volume * k**3, "cm^3 at 1.80 m"),
        "penetrating_vertices_percent": _series(pen.vertices, "%"),
        **pen.part_series,
        "collision_depth": _series(col.depth * k, "cm at 1.80 m"),
        "contact_distance": _series(con.per_frame * k, "cm at 1.80 m", con.count > 0),
        "foot_skate": _series(feet.skate_frame * k, "cm/frame at 1.80 m", feet.skate_valid),
        "ground_penetration": _series(pen.ground * k, "cm at 1.80 m"),
    }
    series.update(contact_hand_series(m))
    if m.deep is not None and m.deep.cause is not None:
        series["deep_frame_cause"] = _series(m.deep.cause.clamp_min(0).float(), DEEP_CAUSE_UNIT, m.deep.cause >= 0, digits=0)
    for c, name in enumerate(m.feet.names):
        if bool(m.feet.available[c]):
            series[f"foot_contact_{name}"] = _series(m.feet.labels[:, c].float(), "0/1", digits=0)
    if err.mpjpe is not None:
        series["mpjpe"] = _series(err.mpjpe * k, "cm at 1.80 m")
    if err.gpe is not None:
        series["global_position_error"] = _series(err.gpe * k, "cm at 1.80 m")
    return series


def summarize(
    m: ClipMeasures,
    original: ClipMeasures | None = None,
    reference: ClipMeasures | None = None,
    source_feet: FootContacts | None = None,
    params: MetricParams | None = None,
) -> MethodMetrics:
    """The summary and per-frame series of ``m``. ``original``: the motion a refinement started from (MPJPE,
    M_i, M_o are measured against it; without it, against ``m`` itself). ``reference``: a ground-truth motion
    on the same character (global position error). ``source_feet``: the source's foot contacts (accuracy, and
    the frames where foot skate is measured; without them the result's own contacts are used)."""
    params = params or MetricParams()
    cm = 100.0
    s = m.scale_to_180
    tol = params.penetration_tolerance_m / s
    pen, col, con = _penetration(m, tol), _collisions(m, original), _contacts(m, params)
    feet, err = _feet(m, source_feet), _errors(m, original, reference)
    k = s * cm
    summary = _summary(m, tol, pen, col, con, feet, err)
    series = _all_series(m, k, pen, col, con, feet, err)
    return MethodMetrics(summary=summary, series=series, penetration_vertices=penetrating_vertices(m, tol, k / cm))


def penetrating_vertices(
    m: ClipMeasures, tolerance_m: float, to_180: float, per_frame: int = 400
) -> PenetratingVertices:
    """Per frame, the (at most ``per_frame``) deepest vertices deeper than ``tolerance_m``; depth in cm at 1.80 m
    (``to_180``: the factor from the body's metres to metres at 1.80 m)."""
    frames, vertex, depth, truncated = m.depths.deepest(tolerance_m, per_frame)
    return PenetratingVertices(
        frame=frames.tolist(),
        vertex=vertex.tolist(),
        depth=[round(v, 2) for v in (depth * to_180 * 100.0).tolist()],
        per_frame_limit=per_frame,
        truncated=truncated,
    )


def _foot_names(feet: FootContacts) -> list[str]:
    from retarget_core.contacts.foot_contact import FOOT_JOINTS

    return [canonical for (_, canonical), j in zip(FOOT_JOINTS, feet.joints, strict=True) if j >= 0]


def _smoothness(joints: Tensor) -> tuple[float | None, float | None]:
    """Mean magnitude of joint acceleration and jerk per frame (m/frame^2, m/frame^3)."""
    acc = jerk = None
    if joints.shape[0] >= 3:
        acc = float((joints[2:] - 2 * joints[1:-1] + joints[:-2]).norm(dim=-1).mean())
    if joints.shape[0] >= 4:
        jerk = float((joints[3:] - 3 * joints[2:-1] + 3 * joints[1:-2] - joints[:-3]).norm(dim=-1).mean())
    return acc, jerk


def compute_metrics(
    character: Character,
    mapping: JointMapping,
    sdf: PartSDF,
    motion: Motion,
    *,
    contacts: ContactConstraints | None = None,
    original: ClipMeasures | None = None,
    reference: ClipMeasures | None = None,
    source_feet: FootContacts | None = None,
    params: MetricParams | None = None,
    source_hand_distances: HandPartDistances | None = None,
    reuse: Reuse | None = None,
    cull_hands: bool = True,
    deep_causes: bool = True,
) -> tuple[MethodMetrics, ClipMeasures]:
    """:func:`measure_clip` then :func:`summarize`; returns the metrics and the measures (reuse them as the
    ``original`` of a later result). ``source_hand_distances`` (``SelfContacts.distances`` of the source):
    adds the false contacts. ``reuse``, ``cull_hands``, ``deep_causes``: see :func:`measure_clip`."""
    measures = measure_clip(character, mapping, sdf, motion, contacts, params=params,
                            source_hand_distances=source_hand_distances, reuse=reuse, cull_hands=cull_hands,
                            deep_causes=deep_causes)  # fmt: skip
    return summarize(measures, original, reference, source_feet, params), measures


__all__ = [
    "LIMBS", "ClipMeasures", "MetricParams", "compute_metrics", "limb_distances", "measure_clip", "part_split",
    "penetration_by_part", "summarize", "vertex_part_clusters",
]  # fmt: skip
