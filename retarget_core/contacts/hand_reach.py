"""Each hand's nearest approach to the judge's body parts on posed frames, with the two points that make it: what
the hand contact stage (:mod:`retarget_core.refine.hand_contacts`) moves hands by.

The parts are the judge's (:mod:`retarget_core.metrics.acceptance_body`: closed parts of the body meshes, by
dominant joint), searched through one triangle tree per part refit to every frame
(:mod:`retarget_core.geometry.triangle_bvh`). A hand is sampled one vertex per ``cell_m`` cell of its rest pose
(1 cm: the distance is within a few millimetres of the judge's, which reads every hand vertex); a sampled vertex
inside the part makes the distance 0. Lengths in metres on the body's own scale.

:class:`PosedParts` (the parts of a chunk of frames, each tree refit on the frames a query needs) is shared with
the arms' penetration (:mod:`retarget_core.contacts.arm_depth`); :class:`MovedParts` reads the same frames moved
several ways (the elbow swivel's turns), posing and refitting again only what moved (:func:`posed_moved`), equal
to posing and refitting everything.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.energy.sdf import vertex_areas
from retarget_core.geometry.bvh_kernels import rows_bounds
from retarget_core.geometry.closest_point import closest_points
from retarget_core.geometry.triangle_bvh import (
    PosedBoxes,
    TriangleBVH,
    build_bvh,
    closest_triangles,
    refit,
    refit_changed,
    winding_numbers,
)
from retarget_core.metrics.acceptance_body import (
    HANDS,
    PARTS,
    AcceptanceBody,
    ClosedPart,
    acceptance_body,
    cached_per_body,
)
from retarget_core.motion import Motion

CHUNK_BUDGET_BYTES = 160 * 2**20  # a chunk's part trees and posed rows: 64 frames of a MakeHuman body fit, a 95k-vertex
# body poses fewer at a time (figures: docs/results.md, "Trees of four triangles a leaf")
HAND_CELL_M = 0.01  # one sampled hand vertex per rest-pose cell of this size (at 1.80 m)
COARSE_HAND_CELL_M = 0.025  # ... for the queries that only ask whether a hand comes near a part
ARM_CELL_M = 0.02  # the arms' penetration check: one arm vertex per cell of this size, and every hand vertex
CACHE_SIZE = 4  # bodies kept in memory
INSIDE_CHECK_M = 0.03  # sampled points this close to a part are tested for inside (deeper ones: a hand in a part)


@dataclass
class ReachBody:
    """Per body: the judge's parts, each hand's sampled vertices ``hand_points[h] (K,)`` (in :data:`HANDS`
    order) and each part's tree over its closed mesh (rest pose)."""

    body: AcceptanceBody
    hand_points: tuple[np.ndarray, ...]
    coarse_hand_points: tuple[np.ndarray, ...]  # the same at COARSE_HAND_CELL_M: where only "within 2 cm?" is asked
    arm_points: tuple[np.ndarray, ...]  # per arm (left, right): its counted vertices (outside the seam band) tested
    # for penetration: one per ARM_CELL_M cell, and every hand vertex
    arm_area: tuple[Tensor, ...]  # per arm ``(K,)``: the surface each stands for (a cell's face; a hand vertex's own)
    arm_cells: tuple[int, ...]  # per arm: how many of ``arm_points`` (the first) are the arm's cells, not its hand
    leg_points: tuple[np.ndarray, ...]  # per leg: counted vertices, one per ARM_CELL_M cell (tested inside the arms)
    leg_area: tuple[Tensor, ...]
    trees: dict[str, TriangleBVH]
    scale: float  # body lengths per length at 1.80 m
    _read: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)  # read_vertices, once

    def chunk_frames(self, most: int) -> int:
        """Frames to pose together, at most ``most``: as many as keep a chunk's :meth:`frame_bytes` within
        :data:`CHUNK_BUDGET_BYTES`."""
        return max(1, min(most, CHUNK_BUDGET_BYTES // max(self.frame_bytes(), 1)))

    def frame_bytes(self) -> int:
        """Bytes one posed frame holds: every part's tree boxes (low and high corners of each node, float64) and
        its :func:`posed_for_reach` rows."""
        read = self.read_vertices()
        return sum(tree.box_bytes() for tree in self.trees.values()) + 24 * (int(read[-1]) + 1 if len(read) else 0)

    def read_vertices(self) -> np.ndarray:
        """Sorted body vertices the measures pose: the sampled hand and arm vertices and every part's (made once:
        every posed chunk asks)."""
        if self._read is None:
            own = [part.vertices for part in self.body.parts if part is not None]
            hands = [*self.hand_points, *self.coarse_hand_points]
            self._read = np.unique(np.concatenate([*hands, *self.arm_points, *self.leg_points, *own]).astype(np.int64))
        return self._read


def one_per_cell(rest: np.ndarray, idx: np.ndarray, cell: float) -> np.ndarray:
    """The first of ``idx (N,)`` in each ``cell``-sized voxel of the rest positions ``rest (V, 3)``, sorted."""
    key = np.floor(rest[idx] / cell).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(idx[first])


def reach_body(character: Character, mapping: JointMapping) -> ReachBody:
    """:func:`build_reach_body`, cached in-process by the character's content (its trees take a second to build)."""
    return cached_per_body(_CACHE, character, mapping, build_reach_body, CACHE_SIZE)


def build_reach_body(character: Character, mapping: JointMapping, cell_m: float = HAND_CELL_M) -> ReachBody:
    """The judge's body of ``character`` with sampled hands and arms and part trees."""
    body = acceptance_body(character, mapping)
    rest = character.vertices.detach().double().numpy()
    scale = character.height / 1.80
    hand_idx = [np.asarray(body.hand_vertices[h], dtype=np.int64) for h in HANDS]
    hands = tuple(one_per_cell(rest, idx, cell_m * scale) for idx in hand_idx)
    coarse = tuple(one_per_cell(rest, idx, COARSE_HAND_CELL_M * scale) for idx in hand_idx)
    vertex_area = vertex_areas(character.vertices.detach().double(), character.faces).double()
    arms, areas, cells = [], [], []
    for h in HANDS:
        counted = (body.part_of_vertex == PARTS.index(f"{h}_arm")) & ~body.seam
        counted[body.hand_vertices[h]] = False
        rest_of_arm = one_per_cell(rest, np.nonzero(counted)[0], ARM_CELL_M * scale)
        hand_all = np.asarray(body.hand_vertices[h], dtype=np.int64)
        hand_counted = hand_all[~body.seam[hand_all]]  # every hand vertex: the hand is what the stage brings near
        arms.append(np.concatenate([rest_of_arm, hand_counted]))
        cells.append(len(rest_of_arm))
        areas.append(torch.cat([torch.full((len(rest_of_arm),), (ARM_CELL_M * scale) ** 2, dtype=torch.float64),
                                vertex_area[torch.from_numpy(hand_counted)]]))  # fmt: skip
    legs = [one_per_cell(rest, np.nonzero((body.part_of_vertex == PARTS.index(f"{h}_leg")) & ~body.seam)[0],
                         ARM_CELL_M * scale) for h in HANDS]  # fmt: skip
    leg_area = tuple(torch.full((len(v),), (ARM_CELL_M * scale) ** 2, dtype=torch.float64) for v in legs)
    trees = {name: build_bvh(part.posed(rest), part.faces) for name, part in zip(PARTS, body.parts, strict=True)
             if part is not None}  # fmt: skip
    return ReachBody(body, hands, coarse, tuple(arms), tuple(areas), tuple(cells), tuple(legs), leg_area, trees, scale)


@dataclass
class Reach:
    """Per query ``(Q,)``: the hand's distance to the part (0 when a sampled point is inside, ``inf`` beyond the
    search bound) and ``(Q, 3)`` the hand point and the surface point of that distance (NaN where ``inf``)."""

    distance: Tensor
    hand_point: Tensor
    surface_point: Tensor


_CACHE: OrderedDict[str, ReachBody] = OrderedDict()


class PosedParts:
    """The parts of one chunk of posed frames ``posed (n, W, 3)`` (:func:`posed_for_reach`): each part's posed
    closed mesh, its refit tree boxes and the box of its own vertices, made the first time a part is asked for."""

    def __init__(self, rb: ReachBody, posed: Tensor) -> None:
        self.rb, self.posed = rb, posed.double()
        self._done: dict[str, tuple[Tensor, PosedBoxes]] = {}
        self._some: dict[str, PosedBoxes] = {}  # trees refit on some of the frames (rows -1: not yet)
        self._boxes: dict[tuple[str, bytes], tuple[Tensor, Tensor]] = {}
        self._parent: tuple[PosedParts, Tensor] | None = None

    def frames(self, idx: Tensor) -> PosedParts:
        """These parts on the chunk's frames ``idx (m,)``: what is already made here is sliced, not made again."""
        out = PosedParts(self.rb, self.posed[idx])
        out._parent = (self, idx)
        return out

    def get(self, name: str) -> tuple[Tensor, PosedBoxes] | None:
        """``(local (n, N + L, 3), boxes)`` of part ``name`` (None when the body has no such part)."""
        closed = self.rb.body.part(name)
        return None if closed is None else self._whole(name, closed)

    def tree_boxes(self, name: str, frames: Tensor) -> PosedBoxes:
        """Part ``name``'s tree boxes, refit on (at least) the chunk's frames ``frames (k,)`` (sorted, unique, not
        empty): the others may be missing (a part is often near the points tested on a few frames only)."""
        closed = self._closed(name)
        if name in self._done or len(frames) == len(self.posed):
            return self._whole(name, closed)[1]
        some = self._some.get(name)
        need = frames if some is None or some.rows is None else frames[some.rows[frames] < 0]
        if len(need):
            some = _with_frames(some, self._made_on(name, closed, need), need, len(self.posed))
            self._some[name] = some
        assert some is not None
        return some

    def box(self, name: str) -> tuple[Tensor, Tensor]:
        """``(n, 1, 3)`` low and high corners of the box of part ``name``'s own vertices on each frame (the root
        box of its tree: the caps' centres lie within)."""
        return self.box_of(name, self._closed(name).vertices)

    def box_of(self, name: str, vertices: np.ndarray) -> tuple[Tensor, Tensor]:
        """``(n, 1, 3)`` the box of ``vertices (K,)``, some of part ``name``'s own, on each frame."""
        key = (name, vertices.tobytes())
        if key not in self._boxes:
            if self._parent is not None and key in self._parent[0]._boxes:
                lo, hi = self._parent[0]._boxes[key]
                self._boxes[key] = lo[self._parent[1]], hi[self._parent[1]]
            else:
                self._boxes[key] = self._made_box(name, vertices)
        return self._boxes[key]

    def _made_box(self, name: str, vertices: np.ndarray) -> tuple[Tensor, Tensor]:
        """:meth:`box_of`, measured on :attr:`posed`."""
        lo, hi = frame_boxes(self.posed, vertices)
        return lo[:, None], hi[:, None]

    def _closed(self, name: str) -> ClosedPart:
        """The body's part ``name`` (it has it)."""
        closed = self.rb.body.part(name)
        if closed is None:
            raise KeyError(f"the body has no part {name}")
        return closed

    def _whole(self, name: str, closed: ClosedPart) -> tuple[Tensor, PosedBoxes]:
        """:meth:`get` of a part the body has."""
        if name not in self._done:
            got = self._sliced(name)
            self._done[name] = got if got is not None else self._made(name, closed)
        return self._done[name]

    def _sliced(self, name: str) -> tuple[Tensor, PosedBoxes] | None:
        """Part ``name`` sliced from the chunk these frames were taken from (:meth:`frames`), if it made it."""
        if self._parent is None or name not in self._parent[0]._done:
            return None
        (local, boxes), idx = self._parent[0]._done[name], self._parent[1]
        if boxes.rows is not None:
            return local[idx], replace(boxes, rows=boxes.rows[idx])
        local = local[idx]
        return local, PosedBoxes(boxes.lo[idx], boxes.hi[idx], local)

    def _made(self, name: str, closed: ClosedPart) -> tuple[Tensor, PosedBoxes]:
        """Part ``name``'s posed closed mesh and its tree refit to it."""
        local = torch.from_numpy(closed.posed(self.posed.numpy())).contiguous()
        return local, refit(self.rb.trees[name], local)

    def _made_on(self, name: str, closed: ClosedPart, frames: Tensor) -> PosedBoxes:
        """Part ``name``'s tree refit on ``frames (k,)`` only (``k`` rows), or taken from the chunk these frames
        were taken from (:meth:`frames`)."""
        if self._parent is not None:
            parent, idx = self._parent
            boxes = parent.tree_boxes(name, idx[frames])
            rows = idx[frames] if boxes.rows is None else boxes.rows[idx[frames]]
            return PosedBoxes(boxes.lo[rows], boxes.hi[rows], boxes.vertices[rows])
        local = torch.from_numpy(closed.posed(self.posed.numpy(), frames.numpy())).contiguous()
        return refit(self.rb.trees[name], local)


class MovedParts(PosedParts):
    """:class:`PosedParts` of the ``m`` frames of ``base`` moved one or more ways (``posed (n, W, 3)``, ``n`` a
    multiple of ``m``: frame ``i`` is base frame ``i % m`` moved), where only the rows of the body vertices
    ``moved (V,)`` (bool) differ from the base's. What lies on none of them is the base's (a part's boxes are
    shared: :attr:`PosedBoxes.rows`); a part on a few of them is refit from the base's boxes where they moved
    (min and max are exact: equal to a full refit)."""

    def __init__(self, rb: ReachBody, posed: Tensor, base: PosedParts, moved: np.ndarray) -> None:
        super().__init__(rb, posed)
        self.base, self.moved = base, moved
        self.base_frame = torch.arange(len(posed)) % len(base.posed)  # (n,) the base frame of each frame

    def _made_box(self, name: str, vertices: np.ndarray) -> tuple[Tensor, Tensor]:
        """:meth:`box_of`: the base's over the vertices that did not move (the same for every way), with the
        box of those that did."""
        moved = self.moved[vertices]
        if moved.all():
            return super()._made_box(name, vertices)
        lo, hi = self.base.box_of(name, vertices[~moved])
        lo, hi = lo[self.base_frame], hi[self.base_frame]
        if moved.any():
            m_lo, m_hi = super()._made_box(name, vertices[moved])
            lo, hi = torch.minimum(lo, m_lo), torch.maximum(hi, m_hi)
        return lo, hi

    def tree_boxes(self, name: str, frames: Tensor) -> PosedBoxes:
        """:meth:`PosedParts.tree_boxes`; a part none of whose vertices moved reads the base's."""
        if self._changed(self._closed(name)).any():
            return super().tree_boxes(name, frames)
        base = self.base.tree_boxes(name, torch.unique(self.base_frame[frames]))
        return replace(base, rows=self.base_frame if base.rows is None else base.rows[self.base_frame])

    def _changed(self, closed: ClosedPart) -> np.ndarray:
        """``(N + L,)`` the part's vertices (its own, then its caps' centres) that moved."""
        caps = np.array([self.moved[loop].any() for loop in closed.cap_loops], dtype=bool)
        return np.concatenate([self.moved[closed.vertices], caps])

    def _made_on(self, name: str, closed: ClosedPart, frames: Tensor) -> PosedBoxes:
        """Part ``name``'s tree on ``frames (k,)`` only (``k`` rows), refit from the base's where it moved."""
        base = self.base.tree_boxes(name, torch.unique(self.base_frame[frames]))
        rows = self.base_frame[frames] if base.rows is None else base.rows[self.base_frame[frames]]
        local = torch.from_numpy(closed.posed(self.posed.numpy(), frames.numpy())).contiguous()
        changed = torch.from_numpy(self._changed(closed))
        return refit_changed(self.rb.trees[name], local, replace(base, rows=rows), changed)

    def _made(self, name: str, closed: ClosedPart) -> tuple[Tensor, PosedBoxes]:
        """Part ``name``: the base's where none of its vertices moved, else refit where they did."""
        base = self.base.get(name)
        assert base is not None  # the same body: the same parts
        rows = self.base_frame if base[1].rows is None else base[1].rows[self.base_frame]
        shared = replace(base[1], rows=rows)  # the base's boxes, each frame reading its base frame's
        changed = self._changed(closed)
        caps = changed[len(closed.vertices) :]
        if not changed.any():
            return base[0][self.base_frame], shared
        if 2 * changed.sum() > len(changed):
            local = torch.from_numpy(closed.posed(self.posed.numpy())).contiguous()
        else:  # the base's, with the moved vertices and caps posed again (ClosedPart.posed of them alone)
            local = base[0][self.base_frame]
            only = replace(closed, vertices=closed.vertices[changed[: len(closed.vertices)]],
                           cap_loops=[loop for loop, c in zip(closed.cap_loops, caps, strict=True) if c])  # fmt: skip
            local[:, torch.from_numpy(np.nonzero(changed)[0])] = torch.from_numpy(only.posed(self.posed.numpy()))
        return local, refit_changed(self.rb.trees[name], local, shared, torch.from_numpy(changed))


def _with_frames(some: PosedBoxes | None, new: PosedBoxes, frames: Tensor, n: int) -> PosedBoxes:
    """``some``, a tree's boxes on some of ``n`` frames (``rows`` -1 where missing), with ``new``, its boxes on
    more ``frames (k,)``, added."""
    if new.rows is not None:  # stored once for several frames: one row per frame here
        new = PosedBoxes(new.lo[new.rows], new.hi[new.rows], new.vertices[new.rows])
    if some is None or some.rows is None:
        rows = torch.full((n,), -1, dtype=torch.long)
        rows[frames] = torch.arange(len(frames))
        return replace(new, rows=rows)
    rows = some.rows.clone()
    rows[frames] = len(some.vertices) + torch.arange(len(frames))
    return PosedBoxes(torch.cat([some.lo, new.lo]), torch.cat([some.hi, new.hi]), torch.cat([some.vertices, new.vertices]),
                      rows)  # fmt: skip


def frame_boxes(posed: Tensor, vertices: np.ndarray) -> tuple[Tensor, Tensor]:
    """``(n, 3)`` low and high corners of the box of the rows ``vertices (K,)`` of each frame of ``posed (n, W,
    3)`` (float64), without gathering them (inf and -inf when ``K`` is 0)."""
    lo, hi = rows_bounds(posed.contiguous().numpy(), vertices)
    return torch.from_numpy(lo), torch.from_numpy(hi)


def hand_reach(rb: ReachBody, posed: Tensor, frame: Tensor, hand: Tensor, part: Tensor, bound: Tensor,
               coarse: bool = False) -> Reach:  # fmt: skip
    """The :class:`Reach` of queries (``frame (Q,)`` into ``posed (n, W, 3)``, ``hand (Q,)`` into :data:`HANDS`,
    ``part (Q,)`` into :data:`PARTS`), each searched up to its ``bound (Q,)``, from the hands' sampled points
    (``coarse``: the coarse ones). Queries whose hand's box lies farther than the bound from the part's box are
    not searched; each part's tree is refit on the frames queried."""
    points = rb.coarse_hand_points if coarse else rb.hand_points
    out = _empty_reach(len(frame))
    posed = posed.double().contiguous()
    boxes = [frame_boxes(posed, p) for p in rb.hand_points]
    hand_lo, hand_hi = (torch.stack([b[i] for b in boxes], dim=1) for i in (0, 1))  # (n, 2, 3)
    for p_i in torch.unique(part).tolist():
        closed = rb.body.part(PARTS[p_i])
        if closed is None:
            continue
        lo, hi = frame_boxes(posed, closed.vertices)  # (n, 3) the part's box (cap centres lie within it)
        sel = torch.nonzero(part == p_i).flatten()
        f, h = frame[sel], hand[sel]
        gap = (torch.maximum(lo[f] - hand_hi[f, h], hand_lo[f, h] - hi[f]).clamp_min(0.0)).norm(dim=-1)
        sel = sel[gap <= bound[sel]]
        if len(sel):
            _part_reach(rb, closed, PARTS[p_i], posed, sel, frame, hand, bound, points, out)
    return out


def _part_reach(rb: ReachBody, closed: ClosedPart, name: str, posed: Tensor, sel: Tensor, frame: Tensor,
                hand: Tensor, bound: Tensor, points: tuple[np.ndarray, ...], out: Reach) -> None:  # fmt: skip
    """:func:`hand_reach` of the queries ``sel`` against one part: its tree refit on their frames only."""
    frames, local_frame = torch.unique(frame[sel], return_inverse=True)
    local = torch.from_numpy(closed.posed(posed.numpy(), frames.numpy()))
    boxes = refit(rb.trees[name], local)
    fine = points is rb.hand_points
    for h in range(len(HANDS)):
        mine = sel[hand[sel] == h]
        f = local_frame[hand[sel] == h]
        if len(mine) == 0 or len(points[h]) == 0:
            continue
        args = (rb.trees[name], (local, boxes), f)
        limit = bound[mine]
        if fine:  # the coarse samples first: the fine search needs only to look nearer than they found
            coarse = _empty_reach(len(out.distance))
            at = posed[:, torch.from_numpy(rb.coarse_hand_points[h])][frames]
            _fill(coarse, mine, *args, at, limit, INSIDE_CHECK_M * rb.scale)
            limit = torch.minimum(limit, coarse.distance[mine] + 1e-9)
            _copy_reach(out, coarse, mine)
        at = posed[:, torch.from_numpy(points[h])][frames]  # the points' rows first: not every vertex of each frame
        _fill(out, mine, *args, at, limit, INSIDE_CHECK_M * rb.scale)


def _empty_reach(q_n: int) -> Reach:
    """A :class:`Reach` of ``q_n`` queries that found nothing."""
    return Reach(torch.full((q_n,), float("inf"), dtype=torch.float64),
                 torch.full((q_n, 3), float("nan"), dtype=torch.float64),
                 torch.full((q_n, 3), float("nan"), dtype=torch.float64))  # fmt: skip


def _copy_reach(out: Reach, other: Reach, rows: Tensor) -> None:
    """``other``'s entries ``rows`` into ``out``."""
    out.distance[rows], out.hand_point[rows], out.surface_point[rows] = (
        other.distance[rows], other.hand_point[rows], other.surface_point[rows])  # fmt: skip


def _fill(out: Reach, sel: Tensor, tree: TriangleBVH, posed_part: tuple[Tensor, PosedBoxes], frame: Tensor,
          points: Tensor, max_distance: Tensor, inside_check: float) -> None:  # fmt: skip
    """:func:`hand_reach` of the queries ``sel`` of one (part, hand), at the part's frames ``frame (q,)``: every
    sampled point ``points (m, K, 3)`` (posed on the part's ``m`` frames) searched, the nearest written into
    ``out`` where one lies within the bound."""
    local, boxes = posed_part
    k = points.shape[1]
    qf = frame.repeat_interleave(k)
    qp = points[frame].reshape(-1, 3)
    d, face = closest_triangles(tree, boxes, qf, qp, max_distance.repeat_interleave(k))
    check = torch.nonzero(d < inside_check).flatten()
    if len(check):
        inside = winding_numbers(tree, boxes, qf[check], qp[check]).abs() > 0.5
        d[check[inside]] = 0.0
    d = d.view(len(sel), k)
    best = d.argmin(dim=1)
    row = torch.arange(len(sel)) * k + best
    nearest = d[torch.arange(len(sel)), best]
    found = torch.isfinite(nearest)  # nothing within the bound: ``out`` keeps what it held
    if not bool(found.any()):
        return
    row, hit = row[found], sel[found]
    out.distance[hit] = nearest[found]
    tri = tree.faces[face[row]]
    corners = [local[qf[row], tri[:, c]] for c in range(3)]
    out.hand_point[hit] = qp[row]
    out.surface_point[hit] = closest_points(qp[row], *corners)


def posed_for_reach(rb: ReachBody, character: Character, motion: Motion, frames: Tensor) -> Tensor:
    """``(n, W, 3)`` the body posed at clip ``frames (n,)``: the rows up to the last vertex the measures read
    (:meth:`ReachBody.read_vertices`; ``W <= V``: accessories stored after the body are left out), only the read
    ones posed (the others zero)."""
    read = torch.from_numpy(rb.read_vertices())
    width = int(read[-1]) + 1 if len(read) else 0
    with torch.no_grad():
        grot, gpos = kinematics.forward_kinematics(motion.skeleton.parents, motion.rotations[frames],
                                                   motion.translations[frames])  # fmt: skip
        make = torch.empty if len(read) == width else torch.zeros  # every row read and written: no zero fill
        posed = make(len(frames), width, 3, dtype=torch.float64)  # double, as the measures read it
        posed[:, read] = character.pose_rows(read, grot, gpos).to(posed.dtype)
    return posed


def posed_chunks(rb: ReachBody, character: Character, motion: Motion, frames: Tensor,
                 most: int = 64) -> Iterator[tuple[Tensor, Tensor]]:  # fmt: skip
    """``(fr (m,), posed (m, W, 3))``: :func:`posed_for_reach` of clip ``frames (n,)``, :meth:`ReachBody.chunk_frames`
    of ``most`` frames at a time."""
    chunk = rb.chunk_frames(most)
    for s in range(0, len(frames), chunk):
        fr = frames[s : s + chunk]
        yield fr, posed_for_reach(rb, character, motion, fr)


@dataclass
class MovedPoses:
    """:func:`posed_for_reach` of ``T`` ways of moving the same ``m`` frames, made from ``base (m, W, 3)``, those
    frames before the moves (double, as :class:`PosedParts` holds it): the rows ``rows (R,)`` posed again from
    the joints' world transforms ``grot (T * m, J, 4)``, ``gpos (T * m, J, 3)`` (way after way) when their ways
    are asked for; ``moved (V,)`` (bool) those rows (the others are the base's)."""

    character: Character
    base: Tensor
    rows: Tensor
    grot: Tensor
    gpos: Tensor
    moved: np.ndarray

    def __len__(self) -> int:
        return len(self.grot) // len(self.base)

    def ways(self, group: int) -> Iterator[tuple[int, Tensor]]:
        """``(first, posed (count * m, W, 3))``: the frames moved ``count`` ways from way ``first`` on, way after
        way, ``group`` ways at a time (fewer in the last). One buffer serves every group (only the moved rows are
        posed and written again, a group at a time: all ``T`` ways at once held a few hundred MB on a large
        body), so each ``posed`` is valid until the next is yielded."""
        m, ways = len(self.base), len(self)
        buffer = self.base.repeat(min(group, ways), 1, 1)
        for first in range(0, ways, group):
            count = min(group, ways - first)
            out, at = buffer[: count * m], slice(first * m, (first + count) * m)
            with torch.no_grad():
                out[:, self.rows] = self.character.pose_rows(self.rows, self.grot[at], self.gpos[at]).to(out.dtype)
            yield first, out


def posed_moved(rb: ReachBody, character: Character, moved: Motion, motion: Motion, frames: Tensor,
                posed: Tensor) -> MovedPoses:  # fmt: skip
    """:func:`posed_for_reach` of ``moved``, ``T * m`` frames: clip ``frames (m,)`` of ``motion`` moved ``T``
    ways, one after another, from ``posed (m, W, 3)``, those frames of ``motion`` posed: only the vertices
    skinned to a joint whose world transform moved are posed again (the others' rows are the same products of
    the same numbers)."""
    read = torch.from_numpy(rb.read_vertices())
    with torch.no_grad():
        grot, gpos = kinematics.forward_kinematics(moved.skeleton.parents, moved.rotations, moved.translations)
        brot, bpos = kinematics.forward_kinematics(motion.skeleton.parents, motion.rotations[frames],
                                                   motion.translations[frames])  # fmt: skip
        same = (grot.view(-1, *brot.shape) == brot).all(dim=-1) & (gpos.view(-1, *bpos.shape) == bpos).all(dim=-1)
        joints = ~same.flatten(0, 1).all(dim=0)  # (J,) the joints moved on some frame
        rows = read[(character.dense_weights()[read][:, joints] != 0).any(dim=1)]
    mask = np.zeros(character.num_vertices, dtype=bool)
    mask[rows.numpy()] = True
    return MovedPoses(character, posed, rows, grot, gpos, mask)


__all__ = ["HAND_CELL_M", "build_reach_body", "PosedParts", "Reach", "ReachBody", "hand_reach", "one_per_cell",
           "posed_chunks", "posed_for_reach", "posed_moved", "MovedParts", "MovedPoses", "reach_body"]
