"""Hand contacts as the judge reads them: a hand that touches a part in the source rests on that part's surface on
the target (not inside it), and a hand that is clear of the body in the source stays clear (issue 22, items 2, 3).

Why: the stages before this one hold contacts through rigid part SDFs and vertex pairs carried from the source.
On stylised characters (a dress skinned across hips and legs, a big rigid head, short arms) those read a contact
as kept where the posed mesh shows the hand 3 to 6 cm off it, and a hand can end within a centimetre of a part it
never touched (docs/collisions.md, "Production characters"). Here the contacts are measured as the judge measures
them, on the judge's closed parts of the posed mesh (:mod:`retarget_core.contacts.hand_reach`), and each hand is
moved by its wrist, with the arm's two-bone IK keeping the elbow's swivel and the hand's world rotation:

1. Wanted moves ``(F, 2, 3)``: per frame and hand, for each part the judge tests it against (head, torso, the
   other arm, the legs), toward the part where the source touches it (within ``contact_m``) and the result is
   farther than ``lost_m``, to ``goal_m`` from it, along the closest pair; away from it where the source is far
   (beyond ``far_m``) and the result is within ``clear_m`` (or in it), to ``clear_m``, along the way out from the
   part's bones (:mod:`retarget_core.contacts.part_axes`: a grazing hand's closest pair points any way); out of a
   part the hand is deeper than ``out_m`` in, to its surface (a hand pressed into a bigger thigh or belly: the
   judge counts its vertices; :mod:`retarget_core.contacts.hand_depth`); the parts' moves summed, at most
   ``max_move_m``.
2. Smooth in time: per hand, a weighted Gaussian mean of the wanted moves (weight 1 where a move is wanted,
   ``hold_weight`` where a touching hand is near enough and is not to be pressed in, ``free_weight`` elsewhere):
   a weighted mean never overshoots, and it is as smooth as the Gaussian whatever the weights.
3. Up to six passes (each measures the one before; a grip's hands, deep in each other, come out over several);
   then the never-worse check of the collision stage on the changed frames, with the arms' penetration read on
   the judge's parts: where it got worse, the change is withdrawn smoothly (:mod:`retarget_core.refine.never_worse`).

Lengths at a 1.80 m character (scaled to the body). Computes on the CPU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.contacts.hand_depth import HandDepth, hand_depths, hand_tests
from retarget_core.contacts.hand_reach import PosedParts, Reach, ReachBody, hand_reach, posed_chunks, reach_body
from retarget_core.contacts.part_axes import away_from_bones, part_bones
from retarget_core.context import RefineContext, StageOutcome, computes_on_cpu
from retarget_core.metrics.acceptance_body import CONTACT_PARTS, HANDS, PARTS, REFERENCE_HEIGHT_M, contact_targets
from retarget_core.motion import Motion
from retarget_core.refine.arms import Arm, arms_of
from retarget_core.refine.collision_check import FrameCheck
from retarget_core.refine.judged_check import never_worse_weights
from retarget_core.refine.judged_contacts import source_hand_distances
from retarget_core.refine.temporal import weighted_smooth
from retarget_core.refine.two_bone_ik import two_bone_ik
from retarget_core.skeleton import subtree

KEPT_M = 0.025  # ACCEPTANCE.md: a source contact is kept when the result's hand is within 2.5 cm
FALSE_M = 0.01  # ... and a hand far from a part on the source makes a false contact within 1 cm of it


@dataclass(frozen=True)
class HandContactParams:
    """Lengths at a 1.80 m character; ACCEPTANCE.md's thresholds in brackets."""

    contact_m: float = 0.015  # a source contact: hand within this of the part [1.5 cm]
    lost_m: float = 0.02  # a touching hand farther than this is moved (kept: within 2.5 cm, less a margin) ...
    goal_m: float = 0.015  # ... to this distance (nearer hands are left alone: a resting hand is not pressed in)
    far_m: float = 0.05  # a source hand this far from a part is clear of it [false contacts: beyond 5 cm]
    clear_m: float = 0.02  # ... and is kept this far from it on the result [counted within 1 cm]
    max_move_m: float = 0.10  # at most this wrist move per frame (farther: another pose, not a lost touch)
    reach_m: float = 0.12  # a touching hand's distance is searched up to this
    smooth_seconds: float = 0.05  # the moves' smoothing in time (a Gaussian's standard deviation): at 0.1 a hand
    # pressed into a thigh for a few frames kept half its depth (docs/contacts.md)
    free_weight: float = 0.1  # a frame without a contact to keep or a false one to avoid: weakly toward no move
    hold_weight: float = 3.0  # a touching hand already near its part: firmly no move (moves nearby barely spread)
    passes: int = 6  # measure-and-move passes at most: each takes a hand further out where the smoothed move fell short
    max_reach: float = 0.995  # the arm's IK reach, as a share of its length
    out_m: float = 0.001  # a hand deeper than this in a part is moved out to its surface [pen %v counts any
    # depth; 5 mm left grips' hands shallowly in each other: docs/results.md, "A hand a millimetre inside"]
    depth_cap_m: float = 0.08  # ... read up to this depth (deeper: the hand is in another pose, not pressed in)
    trade_depth_m: float = 0.005  # a move that keeps more source contacts may deepen the arms up to this [1 cm]


def contact_groups(side: int) -> list[list[int]]:
    """Indices into :data:`PARTS` of the judge's contact parts of hand ``side`` (:data:`CONTACT_PARTS` order:
    head, torso, the other arm, the legs)."""
    return [[PARTS.index(p) for p in parts] for parts in contact_targets(HANDS[side]).values()]


def group_bones(ctx: RefineContext) -> list[list[Tensor]]:
    """Per hand side and contact group (:func:`contact_groups`): ``(B, 2)`` the bones of the group's parts
    (:func:`retarget_core.contacts.part_axes.part_bones`)."""
    bones = part_bones(ctx.target_mapping.joints)
    return [[torch.cat([bones[PARTS[i]] for i in group]) for group in contact_groups(side)] for side in range(2)]


def away_from_groups(gpos: Tensor, state: HandState, bones: list[list[Tensor]]) -> Tensor:
    """``(F, 2, 4, 3)`` per hand and contact group, the unit way from the group's bones (:func:`group_bones`; world
    joint positions ``gpos (F, J, 3)``) to the hand's point nearest the group (``state.hand_point``); zero where not
    measured."""
    out = torch.zeros_like(state.hand_point)
    for side in range(2):
        for g, b in enumerate(bones[side]):
            out[:, side, g] = away_from_bones(state.hand_point[:, side, g, None], gpos, b)[:, 0]
    return out


def source_groups(ctx: RefineContext) -> Tensor:
    """``(F, 2, 4)`` the source's hand distances to the judge's contact parts, at 1.80 m (inf: beyond 5 cm)."""
    dist = source_hand_distances(ctx)
    d = dist.distance * (REFERENCE_HEIGHT_M / ctx.source_body.height)
    cols = {name: i for i, name in enumerate(dist.parts)}
    out = torch.full((d.shape[0], 2, len(CONTACT_PARTS)), float("inf"), dtype=torch.float64)
    for side in range(2):
        for g, group in enumerate(contact_groups(side)):
            have = [cols[PARTS[i]] for i in group if PARTS[i] in cols]
            if have:
                out[:, side, g] = d[:, side, have].amin(dim=-1).double()
    return out


@dataclass
class HandState:
    """The target's hands against the judge's contact parts: ``distance (F, 2, 4)`` (body scale; inf where not
    measured or beyond the search), ``hand_point`` and ``surface_point`` ``(F, 2, 4, 3)`` of that distance."""

    distance: Tensor
    hand_point: Tensor
    surface_point: Tensor


def measure_hands(ctx: RefineContext, rb: ReachBody, motion: Motion, src: Tensor, p: HandContactParams,
                  frames: Tensor, state: HandState | None = None, chunk: int = 64,
                  clear_only: bool = False) -> HandState:  # fmt: skip
    """Measure each (frame, hand, contact part) the stage acts on at clip ``frames (n,)``: where the source touches
    it (searched up to ``reach_m``) or stays clear of it (up to ``clear_m``; ``clear_only``: only these); ``src
    (F, 2, 4)`` from :func:`source_groups`. The other entries keep their figures in ``state`` (a copy is
    returned)."""
    state, acted = _cleared(state, src, p, frames, motion.num_frames, clear_only)
    for fr, posed in posed_chunks(rb, ctx.target, motion, frames[acted[frames]], chunk):
        _measure_queries(rb, posed, fr, src[fr], p, state, clear_only)
    return state


def measure_both(ctx: RefineContext, rb: ReachBody, motion: Motion, src: Tensor, p: HandContactParams,
                 frames: Tensor, state: HandState | None = None, depth: HandDepth | None = None,
                 chunk: int = 64) -> tuple[HandState, HandDepth]:  # fmt: skip
    """:func:`measure_hands` of ``frames (n,)``, and the hands' :class:`HandDepth` there, written into a copy of
    ``depth`` (every clip frame; the others keep their figures): each chunk of frames posed once for both."""
    state, acted = _cleared(state, src, p, frames, motion.num_frames)
    out = HandDepth.empty(motion.num_frames) if depth is None else HandDepth(*(t.clone() for t in vars(depth).values()))
    for fr, posed in posed_chunks(rb, ctx.target, motion, frames, chunk):
        keep = acted[fr]
        if bool(keep.any()):
            _measure_queries(rb, posed[keep], fr[keep], src[fr[keep]], p, state)
        _write_depths(out, fr, hand_depths(PosedParts(rb, posed), p.depth_cap_m * rb.scale))
    return state, out


def _cleared(state: HandState | None, src: Tensor, p: HandContactParams, frames: Tensor, f_n: int,
             clear_only: bool = False) -> tuple[HandState, Tensor]:  # fmt: skip
    """A copy of ``state`` (a new one when None) with the entries measured at ``frames (n,)`` cleared, and ``(F,)``
    the clip frames with an entry the stage acts on."""
    inf, nan = float("inf"), float("nan")
    state = (HandState(torch.full((f_n, 2, 4), inf, dtype=torch.float64), torch.full((f_n, 2, 4, 3), nan, dtype=torch.float64),
                       torch.full((f_n, 2, 4, 3), nan, dtype=torch.float64)) if state is None
             else HandState(state.distance.clone(), state.hand_point.clone(), state.surface_point.clone()))  # fmt: skip
    acted = (src > p.far_m) | ((src < p.contact_m) & (not clear_only))
    f, h, g = torch.nonzero(acted[frames], as_tuple=True)
    state.distance[frames[f], h, g], state.hand_point[frames[f], h, g], state.surface_point[frames[f], h, g] = inf, nan, nan
    return state, acted.flatten(1).any(dim=1)


def _measure_queries(rb: ReachBody, posed: Tensor, frames: Tensor, src: Tensor, p: HandContactParams,
                     state: HandState, clear_only: bool = False) -> None:  # fmt: skip
    """Fill ``state`` at ``frames (n,)`` (``src (n, 2, 4)`` their source distances): each (hand, group) the source
    touches, searched up to ``reach_m`` from the hand's fine samples, and each it stays clear of, up to
    ``clear_m`` from its coarse ones; the nearest of the group's parts."""
    kinds = [(src < p.contact_m, p.reach_m, False)] if not clear_only else []
    for wanted, bound, coarse in [*kinds, (src > p.far_m, p.clear_m, True)]:
        f_i, h_i, g_i = torch.nonzero(wanted, as_tuple=True)
        rows, parts = [], []
        for k in range(2):  # a group holds one or two parts (the legs)
            part = torch.tensor([(contact_groups(h)[g] + [-1])[k] for h, g in zip(h_i.tolist(), g_i.tolist(), strict=True)],
                                dtype=torch.long)  # fmt: skip
            rows.append(torch.nonzero(part >= 0).flatten())
            parts.append(part[rows[-1]])
        row = torch.cat(rows)
        r = hand_reach(rb, posed, f_i[row], h_i[row], torch.cat(parts), torch.full((len(row),), bound * rb.scale), coarse)
        _keep_nearest(state, frames[f_i[row]], h_i[row], g_i[row], r)


def _keep_nearest(state: HandState, f: Tensor, h: Tensor, g: Tensor, r: Reach) -> None:
    """Write each (frame, hand, group) entry's nearest of the reaches ``r`` (rows ``(Q,)``) into ``state``."""
    by_distance = torch.argsort(r.distance, stable=True)
    key = (f * 2 + h) * 4 + g
    order = by_distance[torch.argsort(key[by_distance], stable=True)]  # by entry, nearest first
    counts = torch.unique_consecutive(key[order], return_counts=True)[1]
    k = order[torch.cumsum(counts, 0) - counts]
    state.distance[f[k], h[k], g[k]] = r.distance[k]
    state.hand_point[f[k], h[k], g[k]] = r.hand_point[k]
    state.surface_point[f[k], h[k], g[k]] = r.surface_point[k]


def _write_depths(out: HandDepth, frames: Tensor, got: HandDepth) -> None:
    """``got``, the depths of clip ``frames (n,)``, into ``out`` (every clip frame)."""
    out.depth[frames], out.hand_point[frames], out.surface_point[frames] = got.depth, got.hand_point, got.surface_point


def wrist_positions(gpos: Tensor, arms: list[Arm]) -> Tensor | None:
    """``(F, 2, 3)`` the left and right wrists' world positions, of the joints' ``gpos (F, J, 3)`` (None unless both
    arms are mapped)."""
    if len(arms) != 2:
        return None
    hands = [a.hand for a in sorted(arms, key=lambda a: a.side)]
    return gpos[:, hands].double()


def grip_apart(inside: HandDepth, wrists: Tensor | None, deeper_than: float) -> HandDepth:
    """``inside`` with each hand's way out of the other arm, where both hands are deeper than ``deeper_than`` in
    each other's arm (interlocked fists: a grip), turned away from the other hand's wrist (``wrists (F, 2, 3)``):
    the nearest exits of two interlocked fists point mostly the same way, so the hands would move together and
    not apart (docs/contacts.md, "Two-hand grips")."""
    if wrists is None:
        return inside
    other = hand_tests(0).index("right_arm")  # the other arm's column, the same for both hands
    grip = (inside.depth[:, :, other] > deeper_than).all(dim=1)  # (F,)
    if not bool(grip.any()):
        return inside
    apart = wrists - wrists.flip(1)
    apart = apart / apart.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    out = HandDepth(inside.depth.clone(), inside.hand_point.clone(), inside.surface_point.clone())
    way = apart * inside.depth[:, :, other, None]
    out.surface_point[grip, :, other] = inside.hand_point[grip, :, other] + way[grip]
    return out


def wanted_moves(src: Tensor, state: HandState, inside: HandDepth, scale: float, p: HandContactParams,
                 away: Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Wrist moves ``(F, 2, 3)`` (body scale) toward the parts the source touches and away from those it stays
    clear of (module doc, step 1; ``away (F, 2, 4, 3)`` the unit way out of each part from its bones,
    :func:`away_from_groups`: defined also where the hand is on or in the part), and out of the parts
    a hand is deeper than ``out_m`` in (``inside``), and ``(F, 2)`` how much each frame's move counts in the
    smoothing: ``hold_weight`` where a touching hand is near enough (no move: it is not pressed in), 1 where a move
    is wanted, ``free_weight`` elsewhere; ``scale``: body lengths per length at 1.80 m."""
    d = state.distance / scale
    gap = state.surface_point - state.hand_point
    unit = torch.nan_to_num(gap / gap.norm(dim=-1, keepdim=True).clamp_min(1e-12))
    touch = (src < p.contact_m) & torch.isfinite(d)
    pull = touch & (d > p.lost_m)
    push = (src > p.far_m) & (d < p.clear_m)  # distance 0 (in the part) included: ``away`` gives its way out
    toward = torch.nan_to_num(torch.where(pull, d - p.goal_m, 0.0) * scale)[..., None]
    off = torch.nan_to_num(torch.where(push, p.clear_m - d, 0.0) * scale)[..., None]
    move = (unit * toward + away * off).sum(dim=2)  # (F, 2, 3)
    deep = (inside.depth > p.out_m * scale).any(dim=2)
    move = move + kept_touching(inside.out_moves(p.out_m * scale), unit, touch, torch.nan_to_num((p.goal_m - d) * scale))
    size = move.norm(dim=-1, keepdim=True)
    limit = p.max_move_m * scale
    weight = torch.full(move.shape[:2], p.free_weight, dtype=torch.float64)
    weight = torch.where((pull | push).any(dim=2) | deep, 1.0, weight)
    weight = torch.where((touch & ~pull).any(dim=2) & ~deep, p.hold_weight, weight)
    return move * (limit / size.clamp_min(limit)), weight


def kept_touching(out: Tensor, toward: Tensor, touch: Tensor, slack: Tensor) -> Tensor:
    """``out (F, 2, 3)`` moves out of parts, with the part of them away from a part the hand touches (``touch
    (F, 2, 4)``; ``toward (F, 2, 4, 3)`` the unit way to it, zero where the hand is in it) cut to ``slack (F, 2,
    4)``, how far it may go before the contact is lost: a hand at the crease of thigh and belly slides out of the
    thigh along the belly it rests on, not off it."""
    for g in range(toward.shape[2]):
        u = toward[:, :, g] * touch[:, :, g, None]
        away = (out * u).sum(dim=-1, keepdim=True)
        out = out - u * (away + slack[:, :, g, None].clamp_min(0.0)).clamp_max(0.0)
    return out


def contact_figures(src: Tensor, state: HandState, scale: float, p: HandContactParams) -> dict[str, Any]:
    """The judge's contact figures on the stage's measures: the share of source contacts within 2.5 cm and of far
    (hand, part, frame) within 1 cm (ACCEPTANCE.md); ``src (F, 2, 4)`` at 1.80 m."""
    d = state.distance / scale
    touch, far = src < p.contact_m, src > p.far_m
    n_t, n_f = int(touch.sum()), int(far.sum())
    kept = int(kept_contacts(src, state, scale, p).sum())
    return {"source_contacts": n_t, "preservation": round(kept / n_t, 4) if n_t else None,
            "false_contacts": round(float((d[far] < FALSE_M).double().mean()), 4) if n_f else None}  # fmt: skip


def smooth_moves(move: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """``(F, 2, 3)`` each hand's wanted ``move`` smoothed by :func:`weighted_smooth` with ``weight (F, 2)`` from
    :func:`wanted_moves` (``sigma`` frames)."""
    return torch.stack([weighted_smooth(move[:, side], weight[:, side], sigma) for side in range(2)], dim=1)


def apply_moves(motion: Motion, arms: list[Arm], moves: Tensor, max_reach: float) -> Motion:
    """The motion with each arm solved (two-bone IK) so its wrist moves by ``moves (F, 2, 3)``; the elbow keeps
    its swivel side and the hand its world rotation; frames without a move keep their rotations bit for bit."""
    sk = motion.skeleton
    grot, gpos = motion.global_transforms()
    local = motion.rotations.clone()
    for arm in arms:
        idx = torch.nonzero(moves[:, arm.side].norm(dim=-1) > 1e-7).flatten()
        if idx.numel() == 0:
            continue
        a, b, c = (gpos[idx, j] for j in (arm.upper, arm.fore, arm.hand))
        chain = c - a
        pole = (b - a) - chain * (((b - a) * chain).sum(-1, keepdim=True) / chain.pow(2).sum(-1, keepdim=True).clamp_min(1e-12))
        target = c + moves[idx, arm.side].to(c.dtype)
        a_rot, b_rot = grot[idx, arm.upper], grot[idx, arm.fore]
        new_a, new_b = two_bone_ik(a, b, c, target, pole, a_rot, b_rot, max_reach)
        delta_a, delta_b = rot.mul(new_a, rot.inv(a_rot)), rot.mul(new_b, rot.inv(b_rot))
        local[idx, arm.upper] = rot.normalize(rot.mul(rot.inv(grot[idx, sk.parents[arm.upper]]), new_a))
        fore_parent = rot.mul(delta_a, grot[idx, sk.parents[arm.fore]])
        local[idx, arm.fore] = rot.normalize(rot.mul(rot.inv(fore_parent), new_b))
        below_fore = set(subtree(sk.parents, arm.fore))
        for j in (arm.hand, *arm.followers):  # world rotations kept: the hand, and fingers hung from the forearm
            par = sk.parents[j]
            delta = delta_b if par in below_fore else delta_a
            local[idx, j] = rot.normalize(rot.mul(rot.inv(rot.mul(delta, grot[idx, par])), grot[idx, j]))
    return Motion(sk, motion.fps, local, motion.translations.clone(), motion.name)


def pass_moves(src: Tensor, state: HandState, inside: HandDepth, motion: Motion, arms: list[Arm], scale: float,
               p: HandContactParams, bones: list[list[Tensor]]) -> tuple[Tensor, Tensor]:  # fmt: skip
    """One measure-and-move pass on ``motion`` as measured (``state``, ``inside``): the wanted wrist moves ``(F, 2,
    3)`` (:func:`wanted_moves`, a grip's hands apart, hands clear of parts along ``bones`` from
    :func:`group_bones`) and their smoothing in time ``(F, 2, 3)`` (body scale)."""
    gpos = motion.global_transforms()[1]
    apart = grip_apart(inside, wrist_positions(gpos, arms), p.out_m * scale)
    want, weight = wanted_moves(src, state, apart, scale, p, away_from_groups(gpos, state, bones))
    return want, smooth_moves(want, weight, p.smooth_seconds * motion.fps)


@computes_on_cpu
def run(ctx: RefineContext, motion: Motion, params: HandContactParams | None = None) -> StageOutcome:
    """Hands onto the parts the source touches and clear of those it does not (module doc)."""
    p = params or HandContactParams()
    t0 = time.perf_counter()
    if ctx.source_view.num_frames != motion.num_frames or motion.num_frames == 0:
        return StageOutcome(motion, {"frames_changed": 0, "note": "source frames differ", "seconds": 0.0})
    arms = arms_of(ctx.target_mapping, ctx.target.skeleton.parents)
    rb = reach_body(ctx.target, ctx.target_mapping) if arms else None
    if rb is None or not all(len(h) for h in rb.hand_points):
        return StageOutcome(motion, {"frames_changed": 0, "note": "no mapped arm with a hand mesh", "seconds": 0.0})
    src = source_groups(ctx)
    state, inside = measure_both(ctx, rb, motion, src, p, torch.arange(motion.num_frames))
    first = state
    deep_before = int((inside.depth > p.out_m * rb.scale).any(dim=2).any(dim=1).sum())
    before = contact_figures(src, state, rb.scale, p)
    total = torch.zeros(motion.num_frames, 2, 3, dtype=torch.float64)
    moved_motion, bones = motion, group_bones(ctx)
    for _ in range(p.passes):
        want, step = pass_moves(src, state, inside, moved_motion, arms, rb.scale, p, bones)
        if float(want.abs().max()) == 0.0:
            break
        total = total + step
        again = torch.nonzero(step.norm(dim=-1).amax(dim=1) / rb.scale > 1e-4).flatten()
        moved_motion = apply_moves(motion, arms, total, p.max_reach)
        state, inside = measure_both(ctx, rb, moved_motion, src, p, again, state, inside)
    moved = contact_figures(src, state, rb.scale, p)
    changed = torch.nonzero(total.norm(dim=-1).amax(dim=1) / rb.scale > 1e-4).flatten()
    weight = (never_worse_share(ctx, rb, motion, arms, total, changed, src, (first, state), p) if len(changed)
              else torch.ones(motion.num_frames))  # fmt: skip
    out = apply_moves(motion, arms, total * weight[:, None, None], p.max_reach)
    withdrawn = changed[weight[changed] < 1.0]
    after = contact_figures(src, measure_hands(ctx, rb, out, src, p, withdrawn, state), rb.scale, p)
    report = {"frames_changed": len(changed), "withdrawn_frames": len(withdrawn),
              "max_move_cm": round(float(total.norm(dim=-1).max()) / rb.scale * 100.0, 2),
              "source_contacts": before["source_contacts"], "frames_hand_in_body_before": deep_before,
              **{f"{k}_{when}": figures[k] for when, figures in (("before", before), ("moved", moved), ("after", after))
                 for k in ("preservation", "false_contacts")},
              "seconds": round(time.perf_counter() - t0, 3)}  # fmt: skip
    return StageOutcome(out, report)


def near_clear_parts(src: Tensor, state: HandState, scale: float, p: HandContactParams) -> Tensor:
    """``(F, 2, 4)`` a hand within ``clear_m`` of a part the source keeps it farther than ``far_m`` from."""
    return (src > p.far_m) & (state.distance < p.clear_m * scale)


def never_worse_share(ctx: RefineContext, rb: ReachBody, motion: Motion, arms: list[Arm], total: Tensor,
                      changed: Tensor, src: Tensor, states: tuple[HandState, HandState],
                      p: HandContactParams) -> Tensor:  # fmt: skip
    """``(F,)`` the share of the moves kept per frame (:func:`retarget_core.refine.judged_check.never_worse_weights`;
    ``states``: the measures of the input and of the whole moves): a frame where a hand comes within ``clear_m``
    of a part the source keeps it clear of, and did not on the input, is worse too; a frame whose whole move keeps
    more source contacts than the input did may deepen the arms up to ``trade_depth_m`` (:func:`contact_trade`)."""
    near_before = near_clear_parts(src, states[0], rb.scale, p)
    gained = kept_contacts(src, states[1], rb.scale, p) > kept_contacts(src, states[0], rb.scale, p)

    def moved(weight: Tensor) -> Motion:
        return apply_moves(motion, arms, total * weight[:, None, None], p.max_reach)

    def verdict(out: Motion, frames: Tensor, check: FrameCheck) -> FrameCheck:
        after = measure_hands(ctx, rb, out, src, p, frames, states[0], clear_only=True)
        near = (near_clear_parts(src, after, rb.scale, p)[frames] & ~near_before[frames]).flatten(1).any(dim=1)
        return replace(check, flagged=near, excused=contact_trade(gained[frames], check.max_depth / rb.scale, p))

    return never_worse_weights(ctx, rb, motion, moved, changed, verdict)


def kept_contacts(src: Tensor, state: HandState, scale: float, p: HandContactParams) -> Tensor:
    """``(F,)`` how many of each frame's source contacts (hand, part) the judge reads as kept (within 2.5 cm)."""
    return ((src < p.contact_m) & (state.distance < KEPT_M * scale)).flatten(1).sum(dim=1)


def contact_trade(gained: Tensor, arm_depth: Tensor, p: HandContactParams) -> Tensor:
    """``(n,)`` frames whose deeper arms the never-worse check accepts: their whole move keeps more source contacts
    than the input (``gained (n,)``; fixed, so a partly withdrawn move keeps its excuse) and the arms' deepest
    point ``arm_depth (n,)`` (at 1.80 m) stays within ``trade_depth_m``, short of what the judge counts as a frame
    deeper than 1 cm. A hand on a short-armed
    character's thigh or belly brings its forearm into the body; a hand that touches where the source touches is
    worth a few millimetres of forearm in a soft part (docs/contacts.md)."""
    return gained & (arm_depth <= p.trade_depth_m)
