"""Collision resolution (paper 2's body-part SDFs, DESIGN step 9): limbs, head and, where needed, the upper spine
turned so that they leave the body, contacts kept, smooth, never worse than the input on any frame.

An optimisation resolver on the whole clip at once, in phases over one :class:`Solve` state:

1. set-up (:func:`set_up`): contacts (the detector's and the judge's source contacts it missed), every frame
   measured with all vertices (rigid part SDFs on the judged pairs, and the arms against the posed torso mesh,
   :mod:`collision_mesh`, whose armpit skin follows the arm), the frames to optimise (penetrating, in contact or
   below the floor, with a margin) and the floor points;
2. problem (:func:`set_problem`): a rotation-vector residual per optimised joint on the input's local rotation
   (``q = q_in * exp(r)``), ``r(t)`` a cubic B-spline over knots every few frames (C2 in time, no jitter; zero
   knots give the input back), end-effector targets, and the points the optimiser sees: sentinels (one per cell
   of each limb and the head), denser hand points, the mesh pairs' points and floor points;
3. sentinel pass (:func:`sentinel_pass`): Adam on the knots against the energy (:mod:`collision_solver`);
4. finishing pass (:func:`finishing_pass`): every vertex penetrating on the input and the torso-mesh pairs at the
   pose reached join the points, and a few more steps run;
5. never worse (:func:`never_worse_pass`, :mod:`never_worse`): every changed frame measured with all vertices;
   where a frame got worse, the vertices that went deeper (unseen by the optimiser) join and the finishing steps
   run again on the knots under it (repair), and only then is the residual blended back toward the input;
6. report (:func:`finish`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import roma
import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.context import RefineContext, StageOutcome
from retarget_core.geometry.judged_pairs import judged_allowed
from retarget_core.geometry.triples import sentinel_vertices
from retarget_core.motion import Motion
from retarget_core.refine.collision_check import (
    CONTACT_KEPT_M,
    ContactInstances,
    FrameCheck,
    check_frames,
    contact_instances,
    stage_figures,
)
from retarget_core.refine.collision_mesh import MeshPairs, MeshSetup, mesh_pairs_of_motion, mesh_setup, part_mask
from retarget_core.refine.collision_params import (
    END_EFFECTOR_PULL,
    END_EFFECTOR_WEIGHTS,
    JOINT_STIFFNESS,
    CollisionParams,
    at_fps,
)
from retarget_core.refine.collision_problem import (
    Ground,
    Problem,
    active_frames,
    ee_targets,
    ee_weights,
    exempt_table,
    ground_points,
)
from retarget_core.refine.collision_solver import apply_residual, optimise
from retarget_core.refine.collision_terms import build_terms
from retarget_core.refine.judged_contacts import judged_source_instances, merged_instances
from retarget_core.refine.never_worse import FallbackSettings, NeverWorse, run_never_worse
from retarget_core.refine.temporal import bspline_basis


@dataclass
class Solve:
    """The collision stage's state, shared by its phases. Clip tensors: ``rot_in (F, J, 4)``, ``trans (F, J, 3)``;
    ``knots (N, Jo, 3)`` the residual's B-spline knots; ``points (P,)`` the vertices the optimiser sees."""

    ctx: RefineContext
    motion: Motion
    params: CollisionParams
    rot_in: Tensor
    trans: Tensor
    contacts: ContactInstances
    held: Tensor  # (contacts,) bool: the judge's source contacts the detector missed
    allowed: Tensor  # (S, S) segment pairs measured
    before: FrameCheck
    body: MeshSetup | None
    mesh: MeshPairs | None  # arm vertex x torso triangle pairs found so far (clip frames)
    ground: Ground | None
    active: Tensor  # (Fa,) frames optimised
    names: list[str]  # joints optimised
    timings: dict[str, float] = field(default_factory=dict)
    report: dict[str, Any] = field(default_factory=dict)
    prob: Problem | None = None
    basis: Tensor | None = None  # (F, N) B-spline rows of every clip frame
    knots: Tensor | None = None
    exempt: Tensor | None = None  # (F, S, C) hand x touched cluster per frame
    points: Tensor | None = None
    hand_points: Tensor | None = None  # the points contacts may use (before the finishing pass's extra vertices)
    energy_terms: dict[str, float] = field(default_factory=dict)
    iterations: int = 0
    repairs: int = 0
    guard: NeverWorse | None = None
    mesh_after: MeshPairs | None = None  # the pairs of the last never-worse measurement
    head_before: Tensor | None = None  # (F,) deepest head vertex inside the posed torso on the input (0: none)
    head_count_before: Tensor | None = None  # (F,) head vertices inside the posed torso on the input

    @property
    def scale(self) -> float:
        return self.ctx.sdf.scale_to_180

    @property
    def tol(self) -> float:
        return self.params.penetration_tolerance_m / self.scale

    @property
    def near(self) -> float:
        return self.params.mesh_near_m / self.scale

    @cached_property
    def head(self) -> Tensor | None:
        """``(V,)`` bool: the vertices the judge counts in the head (None without the posed-mesh test)."""
        return None if self.body is None else part_mask(self.body, "head")

    @property
    def joints(self) -> list[int]:
        assert self.prob is not None
        return self.prob.joints.tolist()

    def residual(self) -> Tensor:
        """``(F, Jo, 3)`` rotation vectors of the current knots on every clip frame."""
        assert self.basis is not None and self.knots is not None
        f_n, n = self.basis.shape
        return (self.basis @ self.knots.reshape(n, -1)).reshape(f_n, len(self.names), 3)

    def measure(self, rotations: Tensor, frames: Tensor) -> FrameCheck:
        """All vertices at clip ``frames (n,)`` of ``rotations (F, J, 4)``: SDF figures with the torso-mesh depth
        folded into ``max_depth``; the mesh pairs found are kept in :attr:`mesh_after`."""
        check = check_frames(self.ctx.target, self.ctx.sdf, rotations, self.trans, frames, self.contacts, self.tol,
                             allowed=self.allowed)  # fmt: skip
        self.mesh_after = with_mesh(self.ctx.target, self.body, check, rotations, self.trans, self.near)
        mask = self.head
        if self.mesh_after is not None and self.head_before is not None and mask is not None:  # a sunk chin is worse
            f_n = self.motion.num_frames
            deeper = (head_depth(self.mesh_after, mask, f_n)[frames] - self.head_before[frames]) * self.scale
            assert self.head_count_before is not None
            more = head_count(self.mesh_after, mask, f_n)[frames] > self.head_count_before[frames]
            check.flagged = (deeper > self.params.worse_head_depth_m) | more
        return check


def set_up(ctx: RefineContext, motion: Motion, params: CollisionParams) -> Solve:
    """Phase 1: contacts, the input measured on every frame, the floor points and the frames to optimise."""
    cpu0 = time.process_time()
    sdf, scale = ctx.sdf, ctx.sdf.scale_to_180
    rot_in, trans = motion.rotations.float(), motion.translations.float()
    contacts = contact_instances(sdf, ctx.constraints)
    held = torch.zeros(contacts.count, dtype=torch.bool)
    if params.judged_contacts:
        contacts, held = merged_instances(contacts, judged_source_instances(ctx, rot_in, trans))
    contacts.gap = torch.where(held, params.held_contact_gap_m, params.contact_gap_m) / scale
    allowed = judged_allowed(sdf) if params.judged_pairs_only else sdf.allowed
    f_n = motion.num_frames
    before = check_frames(ctx.target, sdf, rot_in, trans, torch.arange(f_n), contacts,
                          params.penetration_tolerance_m / scale, allowed=allowed)  # fmt: skip
    body = mesh_setup(ctx.target, ctx.target_mapping) if params.use_mesh else None
    mesh = with_mesh(ctx.target, body, before, rot_in, trans, params.mesh_near_m / scale)
    ground = ground_points(ctx, rot_in, trans, params, scale) if params.w_ground > 0 else None
    active = active_frames(before, contacts, f_n, params, scale, motion.fps, ground.low if ground is not None else None)
    names = [n for n in params.joint_stiffness if n in ctx.target_mapping.joints]
    s = Solve(ctx, motion, params, rot_in, trans, contacts, held, allowed, before, body, mesh, ground, active, names)
    if s.head is not None and mesh is not None:
        s.head_before, s.head_count_before = head_depth(mesh, s.head, f_n), head_count(mesh, s.head, f_n)
    s.timings["check_before"] = time.process_time() - cpu0
    s.report["method"] = "optimisation: B-spline rotation residuals on sentinel SDF energy"
    return s


def set_problem(s: Solve) -> None:
    """Phase 2: the optimised joints and frames, the residual basis, the end effectors and the points."""
    t = time.process_time()
    ctx, p = s.ctx, s.params
    joints = ctx.target_mapping.joints
    s.basis = bspline_basis(s.motion.num_frames, at_fps(p.knot_spacing, s.motion.fps))
    ee_names = [n for n in p.end_effectors if n in joints]
    with torch.no_grad():
        _, gpos_in = kinematics.forward_kinematics(ctx.target.skeleton.parents, s.rot_in[s.active], s.trans[s.active])
    s.prob = Problem(
        joints=torch.tensor([joints[n] for n in s.names], dtype=torch.long),
        stiffness=torch.tensor([p.joint_stiffness[n] for n in s.names]),
        frames=s.active, basis=s.basis[s.active], local_in=roma.unitquat_to_rotmat(s.rot_in[s.active]),
        trans=s.trans[s.active], ee_joints=torch.tensor([joints[n] for n in ee_names], dtype=torch.long),
        ee_weight=ee_weights(ctx, s.contacts, s.active, ee_names, p),
        ee_in=ee_targets(ctx, gpos_in, s.active, ee_names, p.ee_source_pull),
    )  # fmt: skip
    s.exempt = exempt_table(ctx, s.contacts)
    s.points = sentinel_points(s)
    s.knots = torch.zeros(s.basis.shape[1], len(s.names), 3)
    s.timings["setup"] = time.process_time() - t


def sentinel_points(s: Solve) -> Tensor:
    """``(P,)`` the vertices the optimiser sees: one sentinel per cell of each limb and the head, the contacts'
    vertices and denser points on both hands (the contact and end-effector terms move every hand), the torso-mesh
    pairs' vertices and the floor points."""
    ctx, p, scale = s.ctx, s.params, s.scale
    verts = ctx.target.vertices.float()
    c = ctx.constraints
    contact_pts = torch.cat([c.i, c.j]).unique() if c.count else torch.zeros(0, dtype=torch.long)
    hands = [seg for n in ("LeftHand", "RightHand") if (seg := ctx.parts.find(n)) is not None]
    if hands:
        contact_pts = torch.cat([contact_pts, sentinel_vertices(ctx.sdf, verts, p.hand_cell_m / scale, hands)])
    mesh_pts = torch.cat([s.mesh.vertex, s.mesh.tri.flatten()]) if s.mesh is not None else contact_pts[:0]
    ground_pts = s.ground.vertex if s.ground is not None else contact_pts[:0]
    sentinels = sentinel_vertices(ctx.sdf, verts, p.sentinel_cell_m / scale)
    return torch.unique(torch.cat([sentinels, contact_pts, mesh_pts, ground_pts]))


def sentinel_pass(s: Solve) -> None:
    """Phase 3: Adam on the knots with the sentinel points (every ``sentinel_frame_stride``-th frame)."""
    assert s.prob is not None and s.points is not None and s.knots is not None and s.exempt is not None
    t, p = time.process_time(), s.params
    coarse = s.prob.every(p.sentinel_frame_stride)
    terms = build_terms(s.ctx, coarse, s.points, s.contacts, s.exempt, p, s.scale, p.candidate_slack_m / s.scale,
                        s.allowed, mesh=s.mesh, ground=s.ground)  # fmt: skip
    s.report["sentinels"] = int(len(s.points))
    s.report["sentinel_triples"] = terms.triples.count
    s.energy_terms = optimise(s.ctx, coarse, terms, s.knots, p.iterations, p.lr, p, s.scale)
    s.iterations = p.iterations
    s.timings["sentinel_loop"] = time.process_time() - t


def finishing_pass(s: Solve) -> None:
    """Phase 4: the torso-mesh pairs at the pose reached and every vertex penetrating on the input join the
    points; a few smaller steps on every optimised frame."""
    assert s.prob is not None and s.points is not None and s.knots is not None and s.exempt is not None
    p, scale = s.params, s.scale
    if s.body is not None and s.mesh is not None:
        with torch.no_grad():
            now = apply_residual(s.rot_in, s.joints, s.residual())
        reached = mesh_pairs_of_motion(s.ctx.target, s.body, now, s.trans, s.active, s.near)
        reached.frame = s.active[reached.frame]
        add_mesh_pairs(s, reached)
    s.hand_points = s.points
    extra = s.before.depth.vertices_of(s.active)  # before's rows are the clip's frames
    if not p.finish_iterations or len(extra) == 0:
        return
    t = time.process_time()
    is_sentinel = torch.zeros(s.ctx.target.num_vertices, dtype=torch.bool)
    is_sentinel[s.points] = True
    s.points = torch.unique(torch.cat([s.points, extra]))
    slack = torch.where(is_sentinel[s.points], p.candidate_slack_m / scale, p.finish_slack_m / scale)
    terms = build_terms(s.ctx, s.prob, s.points, s.contacts, s.exempt, p, scale, slack, s.allowed, s.hand_points,
                        s.mesh, s.ground)  # fmt: skip
    s.report["finish_points"] = int(len(s.points))
    s.report["finish_triples"] = terms.triples.count
    s.energy_terms = optimise(s.ctx, s.prob, terms, s.knots, p.finish_iterations, p.lr * p.finish_lr_fraction, p,
                              scale, within_m=p.finish_within_m)  # fmt: skip
    s.iterations += p.finish_iterations
    s.timings["finish_loop"] = time.process_time() - t


def add_mesh_pairs(s: Solve, pairs: MeshPairs) -> None:
    """Torso-mesh ``pairs`` (clip frames) join the known ones, and their vertices the points."""
    assert s.mesh is not None and s.points is not None
    s.mesh = s.mesh.union(pairs, s.ctx.target.num_vertices)
    s.points = torch.unique(torch.cat([s.points, s.mesh.vertex, s.mesh.tri.flatten()]))


def never_worse_pass(s: Solve) -> Tensor:
    """Phase 5: the never-worse check with repair rounds; the final residual ``(F, Jo, 3)``, scaled per frame by
    ``s.guard.weight``."""
    t, p = time.process_time(), s.params
    frames = torch.nonzero(s.residual().abs().amax(dim=(1, 2)) > p.changed_rad).flatten()
    s.guard = NeverWorse.start(s.before, s.contacts)

    def measure(weight: Tensor, at: Tensor) -> FrameCheck:
        return s.measure(apply_residual(s.rot_in, s.joints, s.residual() * weight[:, None, None]), at)

    fallback = FallbackSettings(p.fallback_rounds, p.fallback_factor, p.fallback_floor, at_fps(p.fallback_ramp, s.motion.fps))
    run_never_worse(s.guard, frames, measure, p, s.scale, fallback, lambda a, w: repair_round(s, a, w), p.repair_rounds)
    s.timings["check_after"] = time.process_time() - t
    return s.residual()


def repair_round(s: Solve, after: FrameCheck, worse: Tensor) -> Tensor | None:
    """The vertices that went deeper on the ``worse`` frames of ``after`` (SDFs or posed torso), unseen by the
    optimiser, join the points; the finishing steps run again on the knots under those frames. The frames to
    measure again, or None when no vertex was missing."""
    assert s.prob is not None and s.points is not None and s.basis is not None and s.guard is not None
    assert s.knots is not None and s.exempt is not None
    frames = after.frames
    extra = deepened_points(s.before, after, worse, s.points, s.tol)
    mesh_new = mesh_inside(s.mesh_after, frames[worse], s.tol, s.head)
    if len(extra) == 0 and (mesh_new is None or mesh_new.count == 0):
        return None
    t, p, resid = time.process_time(), s.params, s.residual()
    ok_contact = after.contact.clone()
    ok_contact[torch.isin(s.contacts.frame, frames[worse])] = float("nan")
    s.guard.merge(FrameCheck(frames[~worse], after.volume[~worse], after.max_depth[~worse], after.count[~worse],
                             after.depth.select_rows(~worse), ok_contact))  # fmt: skip
    free = (s.basis[frames[worse]] > 0).any(0)  # (N,) knots under the worse frames
    prob = s.prob.subset(torch.nonzero((s.basis[s.prob.frames][:, free] > 0).any(1)).flatten())
    s.points = torch.unique(torch.cat([s.points, extra]))
    if s.mesh_after is not None and s.mesh is not None:
        add_mesh_pairs(s, s.mesh_after)
    with torch.no_grad():  # candidate segments chosen at the pose reached, where the vertices went in
        reached = prob.local(s.knots)
    terms = build_terms(s.ctx, prob, s.points, s.contacts, s.exempt, p, s.scale, p.candidate_slack_m / s.scale,
                        s.allowed, s.hand_points, s.mesh, s.ground, select_local=reached)  # fmt: skip
    s.energy_terms = optimise(s.ctx, prob, terms, s.knots, p.finish_iterations, p.lr * p.finish_lr_fraction, p,
                              s.scale, within_m=p.finish_within_m, free=free)  # fmt: skip
    s.iterations += p.finish_iterations
    s.repairs += 1
    new = s.residual()
    moved = (new - resid).abs().amax(dim=(1, 2)) > p.changed_rad
    moved[frames[worse]] = True
    nonzero = new.abs().amax(dim=(1, 2)) > p.changed_rad
    s.guard.restore(torch.nonzero(moved & ~nonzero).flatten())  # the input's again
    s.timings["repair_loop"] = s.timings.get("repair_loop", 0.0) + time.process_time() - t
    return torch.nonzero(moved & nonzero).flatten()


def deepened_points(before: FrameCheck, after: FrameCheck, worse: Tensor, points: Tensor, tol: float) -> Tensor:
    """Vertices (not yet in ``points``) deeper than ``tol`` and deeper than in ``before`` on the ``worse (n,)``
    frames of ``after``."""
    d = after.depth
    hot = worse.index_select(0, d.frame) & (d.depth > tol)
    frame, vertex, depth = after.frames.index_select(0, d.frame[hot]), d.vertex[hot], d.depth[hot]
    deeper = depth > before.depth.value_at(frame, vertex) + tol  # before's rows are the clip's frames
    grown = torch.unique(vertex[deeper])
    return grown[~torch.isin(grown, points)]


def mesh_inside(mesh: MeshPairs | None, frames: Tensor, tol: float, any_depth: Tensor | None = None) -> MeshPairs | None:
    """The pairs of ``mesh`` (clip frames) deeper than ``tol`` on clip ``frames``; those of the vertices
    ``any_depth (V,)`` (bool) inside at any depth."""
    if mesh is None:
        return None
    limit = torch.full_like(mesh.depth, tol) if any_depth is None else torch.where(any_depth[mesh.vertex], 0.0, tol)
    return mesh.select(torch.isin(mesh.frame, frames) & (mesh.depth > limit))


def head_depth(mesh: MeshPairs, head: Tensor, frames: int) -> Tensor:
    """``(frames,)`` the deepest of the vertices ``head (V,)`` (bool) inside the posed torso per clip frame of
    ``mesh`` (0 where none)."""
    return mesh.select(head[mesh.vertex]).max_depth(frames)


def head_count(mesh: MeshPairs, head: Tensor, frames: int) -> Tensor:
    """``(frames,)`` how many of the vertices ``head (V,)`` (bool) lie inside the posed torso (at any depth: the
    judge's head %v counts them) per clip frame of ``mesh``."""
    inside = head[mesh.vertex] & (mesh.depth > 0)
    return torch.zeros(frames, dtype=torch.long).index_add_(0, mesh.frame[inside], torch.ones_like(mesh.frame[inside]))


def with_mesh(ch: Any, body: MeshSetup | None, check: FrameCheck, rotations: Tensor, translations: Tensor,
              near: float) -> MeshPairs | None:  # fmt: skip
    """Arm vertices inside the posed torso and head (or within ``near``) at ``check``'s frames; ``check.max_depth``
    becomes the deeper of the SDF's and the mesh's (in place). The pairs' frames are clip frames."""
    if body is None:
        return None
    mesh = mesh_pairs_of_motion(ch, body, rotations, translations, check.frames, near)
    check.max_depth = torch.maximum(check.max_depth, mesh.max_depth(len(check.frames)))
    mesh.frame = check.frames[mesh.frame]
    return mesh


def finish(s: Solve, out_rot: Tensor, changed: Tensor, t0: float, cpu0: float) -> StageOutcome:
    """Phase 6: the stage's report and result."""
    final = s.guard.final if s.guard is not None else s.before
    if s.params.trace:
        weight = s.guard.weight if s.guard is not None else torch.ones(s.motion.num_frames)
        s.report["trace"] = {"active": s.active.tolist(), "weight": weight.tolist()}
    s.report.update(stage_figures(s.before, final, s.contacts, s.ctx.target.num_vertices, s.scale))
    s.report.update({
        "frames_changed": int(changed.sum()), "frames_optimised": int(len(s.active)), "iterations": s.iterations,
        "held_source_contacts": int(s.held.sum()),
        "energy_terms": {k: round(v, 3) for k, v in s.energy_terms.items()},
        "cpu_timings_s": {k: round(v, 3) for k, v in s.timings.items()}, "seconds": round(time.perf_counter() - t0, 3),
        "cpu_seconds": round(time.process_time() - cpu0, 3),
    })  # fmt: skip
    m = s.motion
    return StageOutcome(Motion(m.skeleton, m.fps, out_rot.to(m.rotations.dtype), m.translations.clone(), m.name), s.report)


def resolve(ctx: RefineContext, motion: Motion, params: CollisionParams | None = None) -> StageOutcome:
    """Collision resolution of ``motion`` (on ``ctx.target``'s skeleton, ``F`` frames); see the module doc."""
    t0, cpu0 = time.perf_counter(), time.process_time()
    s = set_up(ctx, motion, params or CollisionParams())
    ctx.report_progress(0.3)
    out_rot, changed = s.rot_in, torch.zeros(motion.num_frames, dtype=torch.bool)
    if len(s.active) and s.names:
        set_problem(s)
        sentinel_pass(s)
        ctx.report_progress(0.6)
        finishing_pass(s)
        ctx.report_progress(0.8)
        resid = never_worse_pass(s)
        assert s.guard is not None
        weight = s.guard.weight
        out_rot = rot.normalize(apply_residual(s.rot_in, s.joints, resid * weight[:, None, None]))
        changed = resid.abs().amax(dim=(1, 2)) * weight > s.params.changed_rad
        out_rot[~changed] = s.rot_in[~changed]
        s.report["fallback_frames"] = int((weight < 1 - 1e-6).sum())
        s.report["settle_rounds"] = s.guard.settle_rounds
        s.report["repair_rounds"] = s.repairs
    outcome = finish(s, out_rot, changed, t0, cpu0)
    ctx.report_progress(1.0)
    return outcome


def run(ctx: RefineContext, motion: Motion) -> StageOutcome:
    """The stage entry point (``refine`` registry): :func:`resolve` with the default settings."""
    return resolve(ctx, motion)


__all__ = ["CONTACT_KEPT_M", "CollisionParams", "END_EFFECTOR_PULL", "END_EFFECTOR_WEIGHTS", "JOINT_STIFFNESS",
           "Solve", "resolve", "run"]  # fmt: skip
