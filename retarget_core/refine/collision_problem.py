"""What the collision stage optimises and toward what: the optimised joints and frames with their B-spline
residual basis (:class:`Problem`), the frames that need it, the end effectors' targets and weights, and the floor
points of the hands and feet."""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.body_parts import CLUSTERS
from retarget_core.context import RefineContext
from retarget_core.geometry.point_poser import PointPoser, rotvec_to_matrix
from retarget_core.geometry.triples import sentinel_vertices
from retarget_core.refine.collision_check import ContactInstances, FrameCheck
from retarget_core.refine.collision_params import CollisionParams, at_fps
from retarget_core.refine.floor import planted_feet


@dataclass
class Problem:
    """One clip's optimisation: optimised joints and frames, the residual basis, the input pose."""

    joints: Tensor  # (Jo,) optimised skeleton joints
    stiffness: Tensor  # (Jo,)
    frames: Tensor  # (Fa,) optimised clip frames
    basis: Tensor  # (Fa, N) B-spline rows of those frames
    local_in: Tensor  # (Fa, J, 3, 3) input local rotation matrices
    trans: Tensor  # (Fa, J, 3)
    ee_joints: Tensor  # (E,)
    ee_weight: Tensor  # (Fa, E)
    ee_in: Tensor  # (Fa, E, 3)

    def every(self, stride: int) -> Problem:
        """The same problem on every ``stride``-th optimised frame (the residual is smooth over knots every few
        frames, so fewer frames still constrain every knot)."""
        return self if stride <= 1 else self.subset(torch.arange(0, len(self.frames), stride))

    def subset(self, k: Tensor) -> Problem:
        """The problem on optimised frames ``k`` (indices into :attr:`frames`)."""
        return Problem(self.joints, self.stiffness, self.frames[k], self.basis[k], self.local_in[k], self.trans[k],
                        self.ee_joints, self.ee_weight[k], self.ee_in[k])  # fmt: skip

    def residual(self, knots: Tensor) -> Tensor:
        """``(Fa, Jo, 3)`` rotation vectors of the knots ``(N, Jo, 3)``."""
        return (self.basis @ knots.reshape(knots.shape[0], -1)).reshape(len(self.frames), len(self.joints), 3)

    def local(self, knots: Tensor) -> Tensor:
        """Local rotation matrices ``(Fa, J, 3, 3)`` with the residual applied."""
        turned = self.local_in.index_select(1, self.joints) @ rotvec_to_matrix(self.residual(knots))
        return self.local_in.index_copy(1, self.joints, turned)




GROUND_SEGMENTS: tuple[str, ...] = ("LeftHand", "RightHand", "LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase")


@dataclass
class Ground:
    """Floor points of the hands and feet: ``vertex (G,)`` character vertices, ``floor (F, G)`` their lowest allowed
    height (feet: 0, or the input's height where a foot is already below the floor; hands: 0 on frames where the
    source has a foot planted, else ``-inf``, no bound), ``low (F,)`` the input's lowest bounded point, at most 0."""

    vertex: Tensor
    floor: Tensor
    low: Tensor


def ground_points(ctx: RefineContext, rot_in: Tensor, trans: Tensor, params: CollisionParams, scale: float) -> Ground:
    """The floor points (:class:`Ground`) on the input ``rot_in (F, J, 4)``, ``trans (F, J, 3)``: the stage's
    turns (the end-effector pull toward the source's hips-relative positions, legs turned out of the arms) may not
    put a foot through the floor, nor one already below it deeper. A hand below the floor is turned up by its arm
    only beside a planted foot (a bend to the floor on shorter legs), where the floor stage may not lift the body off
    that foot; elsewhere (a cartwheel on a capture that sinks) its points bound nothing, and the floor stage's lift
    of the whole body keeps the pose (turning the arms up there cost 1 to 5 cm of end-effector error). The hands'
    points stay among the optimiser's points either way: a hand's contacts need them."""
    segs = [s for n in GROUND_SEGMENTS if (s := ctx.parts.find(n)) is not None]
    if not segs:
        e = torch.zeros(0, dtype=torch.long)
        return Ground(e, torch.zeros(len(rot_in), 0), torch.zeros(len(rot_in)))
    pts = sentinel_vertices(ctx.sdf, ctx.target.vertices.float(), params.ground_cell_m / scale, segs)
    poser = PointPoser(ctx.target, pts, ctx.parts.joints)
    with torch.no_grad():
        y = poser(roma.unitquat_to_rotmat(rot_in), trans)[0][..., 1]  # (F, G)
    is_hand = torch.tensor([ctx.parts.names[int(p)].endswith("Hand") for p in ctx.parts.vertex_part[pts]])
    held = is_hand[None] & planted_feet(ctx).any(-1)[: len(y), None]  # (F, G): hands beside a planted foot
    floor = torch.where(is_hand[None], torch.where(held, 0.0, -torch.inf), torch.clamp(y, max=0.0))
    bounded = torch.where(torch.isfinite(floor), y, torch.inf)  # a hand free of the floor marks no frame
    return Ground(pts, floor, bounded.amin(1).clamp(max=0.0) if y.shape[1] else torch.zeros(len(rot_in)))


def exempt_table(ctx: RefineContext, contacts: ContactInstances) -> Tensor:
    """``(F, S, 6)`` bool: hand segment x touched cluster per frame (penetration tolerated there)."""
    ex = torch.zeros(ctx.num_frames, ctx.parts.num_parts, len(CLUSTERS), dtype=torch.bool)
    if contacts.count:
        ex[contacts.frame, contacts.hand, contacts.cluster] = True
    return ex



def active_frames(check: FrameCheck, contacts: ContactInstances, frames: int, params: CollisionParams, scale: float,
                   fps: float = 30.0, low: Tensor | None = None) -> Tensor:  # fmt: skip
    """Frames to optimise: penetrating, in contact or with a hand or foot below the floor (``low (F,)``, m),
    dilated by the margin."""
    marked = torch.zeros(frames, dtype=torch.bool)
    marked[check.frames[check.max_depth * scale > params.penetration_tolerance_m]] = True
    if low is not None and len(low) == frames:
        marked |= low * scale < -params.ground_tolerance_m
    if contacts.count:
        marked[contacts.frame] = True
    if not bool(marked.any()):
        return torch.zeros(0, dtype=torch.long)
    k = at_fps(params.active_margin, fps)
    dil = torch.nn.functional.max_pool1d(marked.float()[None, None], 2 * k + 1, stride=1, padding=k)[0, 0] > 0
    return torch.nonzero(dil).flatten()



def ee_targets(ctx: RefineContext, gpos_in: Tensor, frames: Tensor, names: list[str], pull: dict[str, float]) -> Tensor:
    """``(Fa, E, 3)`` end-effector targets at clip ``frames (Fa,)``: the input's positions ``gpos_in (Fa, J, 3)``,
    moved by ``pull[name]`` (0 when absent) toward the source's (``ctx.source_view`` on its own body) relative to
    the hips, scaled by the bodies' heights."""
    tm, sm = ctx.target_mapping.joints, ctx.source_mapping.joints
    ee_in = gpos_in[:, [tm[n] for n in names]]
    src = ctx.source_view
    w = torch.tensor([pull.get(n, 0.0) for n in names])
    if not bool((w > 0).any()) or "Hips" not in sm or any(n not in sm for n in names) or src.num_frames < int(frames.max()) + 1:
        return ee_in
    with torch.no_grad():
        _, g_src = kinematics.forward_kinematics(ctx.source_body.skeleton.parents, src.rotations[frames].float(),
                                                 src.translations[frames].float())  # fmt: skip
    k = ctx.target.height / ctx.source_body.height
    rel = (g_src[:, [sm[n] for n in names]] - g_src[:, sm["Hips"] : sm["Hips"] + 1]) * k
    target = gpos_in[:, tm["Hips"] : tm["Hips"] + 1] + rel
    return ee_in + w[None, :, None] * (target - ee_in)


def ee_weights(ctx: RefineContext, contacts: ContactInstances, frames: Tensor, names: list[str],
                params: CollisionParams) -> Tensor:  # fmt: skip
    """``(Fa, E)`` end-effector weights at clip ``frames (Fa,)``: ``params.end_effectors``, and
    ``contact_ee_weight`` for a hand on the frames it is in contact, ``planted_foot_ee_weight`` for a foot on
    the frames the source has it planted (``ctx.planted``)."""
    w = torch.tensor([params.end_effectors[n] for n in names]).expand(len(frames), -1).clone()
    if ctx.planted is not None:
        for e, n in enumerate(names):
            if n in ("LeftFoot", "RightFoot"):
                planted = ctx.planted[frames, 0 if n == "LeftFoot" else 1].bool()
                w[planted, e] = params.planted_foot_ee_weight
    if contacts.count == 0:
        return w
    pos_of = torch.full((ctx.num_frames,), -1, dtype=torch.long)
    pos_of[frames] = torch.arange(len(frames))
    for e, n in enumerate(names):
        seg = ctx.parts.find(n)
        if seg is None or not n.endswith("Hand"):
            continue
        f = pos_of[contacts.frame[contacts.hand == seg]]
        w[f[f >= 0], e] = min(params.contact_ee_weight, params.end_effectors[n])
    return w



__all__ = ["GROUND_SEGMENTS", "Ground", "Problem", "active_frames", "ee_targets", "ee_weights", "exempt_table", "ground_points"]
