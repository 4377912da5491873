"""Props above the floor: a prop on a bone of its own (a staff, a sword, a shield: accessory meshes skinned to a
joint the canonical skeleton does not have, hung from a hand) turned at its grip where it would go below the
floor (ACCEPTANCE.md: ground penetration reads the lowest vertex of the whole character).

Why: a prop follows its bone's rest pose relative to the hand. A staff held upright in a game character's rest pose
hangs down its length from a hand that the source holds at the hip: the hard split's Cleric read a judged ground
penetration of 10.4 cm on CMU 02_06 from its staff alone (docs/meshes.md), and the floor stage cannot lift the body
for it (accessories do not count there: the feet would float).

How, per prop (the topmost unmapped joint whose skin moves accessory vertices only) and frame where a vertex is
more than ``sunk_m`` under the floor: the least turn either way about the prop's joint (its grip), about the
horizontal axis across the prop's long axis (across the hips' facing where it hangs plumb), that puts every vertex
``float_m`` above the floor, and how far the turn may go before another vertex goes under (a staff gripped at its
middle: its other end); none where no turn is enough (a hand at the floor). The turn's angle over time is the
least-jerk curve within those bounds (:func:`retarget_core.refine.floor.least_jerk_lift`), its axis the
need-weighted Gaussian mean of the frames'; a few passes. The body's joints keep their rotations bit for bit.

Lengths at a 1.80 m character (scaled to the body). Computes on the CPU.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.context import RefineContext, StageOutcome, computes_on_cpu
from retarget_core.motion import Motion
from retarget_core.refine.floor import least_jerk_lift
from retarget_core.refine.temporal import weighted_smooth
from retarget_core.skeleton import subtree

REFERENCE_HEIGHT_M = 1.80
REST_FORWARD = (0.0, 0.0, 1.0)  # normalised rest poses face +Z


@dataclass(frozen=True)
class PropParams:
    """Lengths at a 1.80 m character."""

    float_m: float = 0.002  # the prop's lowest vertex is put this far above the floor [ground penetration > 0]
    max_turn_deg: float = 120.0  # turns up to this: a staff gripped at its middle may need it near the horizontal
    sunk_m: float = 0.001  # frames whose prop is deeper than this under the floor are turned
    forward_share: float = 0.2  # the hips' facing's share in the turn axis: the axis where a prop hangs plumb
    axis_sigma_seconds: float = 0.1  # the turn axis's smoothing in time (a Gaussian's standard deviation)
    size_weight: float = 1e-4  # the turn's size against its jerk (floor.least_jerk_lift): zero away from need
    passes: int = 3  # measure-and-turn passes at most
    least_turn_deg: float = 0.05  # a smaller turn is none (the least-jerk curve's far tails): those frames keep theirs


@dataclass(frozen=True)
class Prop:
    """One prop: its joint and ``vertices (N,)``, the accessory vertices its subtree's skin moves."""

    joint: int
    vertices: Tensor


def find_props(character: Character, mapping: JointMapping) -> list[Prop]:
    """The character's props: the topmost joints, neither canonical nor mapped extras and with none below them,
    whose subtree moves accessory vertices only (at least one)."""
    parents = character.skeleton.parents
    mapped = {j for j in (*mapping.joints.values(), *mapping.extras.values()) if j is not None}
    moved_by = _influenced(character)
    body = character.body_vertices
    props: list[Prop] = []
    taken: set[int] = set()
    for j in range(len(parents)):
        if j in mapped or parents[j] in taken or parents[j] < 0:
            continue
        below = subtree(parents, j)
        if mapped.intersection(below):
            continue
        verts = torch.nonzero(moved_by[:, below].any(dim=1)).flatten()
        if len(verts) and not bool(body[verts].any()):
            props.append(Prop(j, verts))
            taken.update(below)
    return props


def _influenced(character: Character) -> Tensor:
    """``(V, J)`` bool: vertex ``v`` has a positive skin weight on joint ``j``."""
    out = torch.zeros(character.num_vertices, character.skeleton.num_joints, dtype=torch.bool)
    rows = torch.arange(character.num_vertices)[:, None].expand_as(character.skin_joints)
    out[rows[character.skin_weights > 0], character.skin_joints[character.skin_weights > 0]] = True
    return out


def needed_turns(posed: Tensor, pivot: Tensor, long_axis: Tensor, forward: Tensor, p: PropParams,
                 scale: float) -> tuple[Tensor, Tensor]:  # fmt: skip
    """``(F, 3)`` per frame the rotation vector (world) about ``pivot (F, 3)`` that puts every one of the prop's
    posed vertices ``posed (F, N, 3)`` ``float_m`` above the floor, on frames where one is deeper than ``sunk_m``
    under it (zero elsewhere): about the horizontal axis across the prop's ``long_axis (F, 3)`` (unit; where it
    is plumb, across ``forward (F, 3)``, the hips' facing), by the least angle either way up to ``max_turn_deg``
    (none where no angle is enough), and ``(F,)`` the most it may turn that way
    (:func:`least_angle`; inf where no turn is needed)."""
    sunk = posed[..., 1].min(dim=-1).values < -p.sunk_m * scale
    up = torch.tensor([0.0, 1.0, 0.0], dtype=posed.dtype).expand_as(long_axis)
    axis = torch.linalg.cross(up, long_axis + p.forward_share * forward)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    angle = torch.zeros(len(posed), dtype=posed.dtype)
    room = torch.full_like(angle, float("inf"))
    if bool(sunk.any()):
        rel = posed[sunk] - pivot[sunk, None]
        angle[sunk], room[sunk] = least_angle(rel, axis[sunk], pivot[sunk, 1], p.float_m * scale,
                                              math.radians(p.max_turn_deg))  # fmt: skip
    return axis * angle[:, None], room


def least_angle(rel: Tensor, axis: Tensor, pivot_y: Tensor, floor: float, most: float,
                grid: int = 24) -> tuple[Tensor, Tensor]:  # fmt: skip
    """``(F,)`` the angle in ``[-most, most]`` nearest zero by which turning the points ``rel (F, N, 3)`` (from the
    pivot, at height ``pivot_y (F,)``) about the unit ``axis (F, 3)`` puts them all at or above ``floor``, and
    ``(F,)`` how far (in size) the turn may go on that side before a point goes under it again (a staff gripped
    at its middle: its other end); where no angle does (a hand at the floor), 0 and inf: no turn is asked for. A
    grid each way, then bisection toward zero."""
    along = (rel * axis[:, None]).sum(-1, keepdim=True) * axis[:, None]  # the points' part along the axis
    a = along[..., 1] + pivot_y[:, None]  # (F, N): height = a + b cos t + c sin t
    b = (rel - along)[..., 1]
    c = torch.linalg.cross(axis[:, None].expand_as(rel), rel)[..., 1]

    def lowest(t: Tensor) -> Tensor:
        return (a + b * torch.cos(t)[:, None] + c * torch.sin(t)[:, None]).min(dim=-1).values

    mags = torch.linspace(0.0, most, grid + 1, dtype=rel.dtype)
    sides = [torch.stack([lowest((sign * m).expand(len(rel))) for m in mags], dim=1) >= floor for sign in (1.0, -1.0)]
    first = [torch.where(ok.any(dim=1), ok.double().argmax(dim=1), grid + 1) for ok in sides]  # (F,) each
    sign = torch.where(first[1] < first[0], -1.0, 1.0).to(rel.dtype)
    k = torch.minimum(first[0], first[1])
    feasible = k <= grid
    ok = torch.where((sign > 0)[:, None], sides[0], sides[1])
    later_bad = ~ok & (torch.arange(grid + 1) > k.clamp(max=grid)[:, None])
    end = torch.where(later_bad.any(dim=1), later_bad.double().argmax(dim=1) - 1, torch.full_like(k, grid))
    hi = torch.where(feasible, sign * mags[k.clamp(max=grid)], 0.0)
    lo = torch.where(feasible & (k > 0), sign * mags[(k - 1).clamp(min=0)], hi)
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        good = lowest(mid) >= floor
        hi = torch.where(feasible & good, mid, hi)
        lo = torch.where(feasible & ~good, mid, lo)
    room = torch.where(feasible, mags[end.clamp(min=0)], float("inf"))
    return hi, torch.maximum(room, hi.abs())


def long_axes(character: Character, motion: Motion, prop: Prop) -> Tensor:
    """``(F, 3)`` the prop's long axis (the principal direction of its rest vertices) carried by its joint's world
    rotation on every frame of ``motion`` (unit; its sign is arbitrary)."""
    rest = character.vertices[prop.vertices].double()
    direction = torch.linalg.svd(rest - rest.mean(dim=0), full_matrices=False).Vh[0]
    rest_rot = character.skeleton.rest_global()[0][prop.joint].double()
    grot = motion.global_transforms()[0][:, prop.joint].double()
    carried = rot.mul(grot, rot.inv(rest_rot).expand_as(grot))
    return rot.apply(carried, direction.expand(len(grot), 3))


def eased_turns(need: Tensor, room: Tensor, fps: float, p: PropParams) -> Tensor:
    """``(F, 3)`` the turns ``need (F, 3)`` (rotation vectors) eased in time: the angle the least-jerk curve at or
    above each frame's and within its ``room (F,)``, the axis the need-weighted Gaussian mean of the frames'."""
    angle = need.norm(dim=-1)
    if not bool((angle > 0).any()):
        return need
    eased = least_jerk_lift(angle, room, fps, p.size_weight).clamp_min(0.0)
    eased = torch.where(eased < math.radians(p.least_turn_deg), 0.0, eased)
    axis = need / angle[:, None].clamp_min(1e-12)
    mean = weighted_smooth(axis, angle, p.axis_sigma_seconds * fps)  # (F, 3) zero far from any need
    size = mean.norm(dim=-1)
    return _nearest_filled(mean / size[:, None].clamp_min(1e-12), size > 1e-12) * eased[:, None]


def _nearest_filled(axis: Tensor, known: Tensor) -> Tensor:
    """``axis (F, 3)`` with the rows not ``known (F,)`` taken from the nearest known row (the eased angle's ramps
    can reach beyond the axis's smoothing window)."""
    at = torch.nonzero(known).flatten()
    frames = torch.arange(len(axis))
    right = torch.searchsorted(at, frames).clamp(max=len(at) - 1)
    left = (right - 1).clamp(min=0)
    nearest = torch.where((frames - at[left]).abs() <= (at[right] - frames).abs(), at[left], at[right])
    return axis[nearest]


def turned(motion: Motion, joint: int, turn: Tensor) -> Motion:
    """``motion`` with ``joint``'s world rotation pre-multiplied by the rotations ``turn (F, 3)`` (rotation
    vectors), about its own position: its local rotation changes, its subtree follows."""
    grot, _ = motion.global_transforms()
    parent = motion.skeleton.parents[joint]
    angle = turn.norm(dim=-1)
    axis = turn / angle[:, None].clamp_min(1e-12)
    new_world = rot.mul(rot.axis_angle(axis.to(grot.dtype), angle.to(grot.dtype)), grot[:, joint])
    local = motion.rotations.clone()
    at = angle > 0  # the other frames keep their rotation bit for bit
    local[at, joint] = rot.normalize(rot.mul(rot.inv(grot[at, parent]), new_world[at])).to(local.dtype)
    return Motion(motion.skeleton, motion.fps, local, motion.translations.clone(), motion.name)


def facing(motion: Motion, hips: int) -> Tensor:
    """``(F, 3)`` the hips' facing, horizontal and unit (the rest pose's forward turned by the hips)."""
    grot, _ = motion.global_transforms()
    f = rot.apply(grot[:, hips], torch.tensor(REST_FORWARD, dtype=grot.dtype).expand(len(grot), 3))
    f = f * torch.tensor([1.0, 0.0, 1.0], dtype=f.dtype)
    return f / f.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def lift_prop(character: Character, motion: Motion, prop: Prop, hips: int, p: PropParams) -> tuple[Motion, Tensor]:
    """``motion`` with ``prop`` turned above the floor (module doc) and ``(F,)`` the angle turned per frame."""
    scale = character.height / REFERENCE_HEIGHT_M
    total = torch.zeros(motion.num_frames, dtype=motion.rotations.dtype)
    out = motion
    for _ in range(p.passes):
        grot, gpos = out.global_transforms()
        posed = character.pose_rows(prop.vertices, grot, gpos)
        need, room = needed_turns(posed.double(), gpos[:, prop.joint].double(), long_axes(character, out, prop),
                                  facing(out, hips).double(), p, scale)  # fmt: skip
        if not bool((need.norm(dim=-1) > 0).any()):
            break
        turn = eased_turns(need, room, out.fps, p)
        total = total + turn.norm(dim=-1).to(total.dtype)
        out = turned(out, prop.joint, turn)
    return out, total


@computes_on_cpu
def run(ctx: RefineContext, motion: Motion, params: PropParams | None = None) -> StageOutcome:
    """Props turned at their grip above the floor (module doc). Report: the props, frames changed, the largest
    turn (degrees), the props' lowest vertex before and after (cm at 1.80 m, the lowest over the clip)."""
    p = params or PropParams()
    t0 = time.perf_counter()
    character = ctx.target
    hips = ctx.target_mapping.joints.get("Hips")
    props = find_props(character, ctx.target_mapping) if hips is not None else []
    report: dict[str, object] = {"props": [character.skeleton.names[q.joint] for q in props]}
    if hips is None or not props:
        return StageOutcome(motion, {**report, "frames_changed": 0, "seconds": round(time.perf_counter() - t0, 4)})
    out, changed, largest = motion, torch.zeros(motion.num_frames, dtype=torch.bool), 0.0
    with torch.no_grad():
        lows = [_lowest(character, motion, q) for q in props]
        for q in props:
            out, angle = lift_prop(character, out, q, hips, p)
            changed |= angle > 0
            largest = max(largest, float(angle.max()))
        after = [_lowest(character, out, q) for q in props]
    to_cm = 100.0 * REFERENCE_HEIGHT_M / character.height
    report.update(frames_changed=int(changed.sum()), max_turn_deg=round(math.degrees(largest), 2),
                  lowest_cm_before=round(min(lows) * to_cm, 2), lowest_cm_after=round(min(after) * to_cm, 2),
                  seconds=round(time.perf_counter() - t0, 4))  # fmt: skip
    return StageOutcome(out, report)


def _lowest(character: Character, motion: Motion, prop: Prop) -> float:
    """The lowest height of ``prop``'s vertices over the clip (body scale)."""
    grot, gpos = motion.global_transforms()
    return float(character.pose_rows(prop.vertices, grot, gpos)[..., 1].min())


__all__ = ["Prop", "PropParams", "eased_turns", "find_props", "lift_prop", "needed_turns", "run", "turned"]
