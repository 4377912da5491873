"""Refinement stage ``learned_collisions``: paper 2's per-limb learned collision resolver (trained here by
``retarget train collisions``, weights in ``retarget_core/data/models/collisions.pt``, card in
``docs/model-collisions.md``), run before the optimisation resolver ``collisions``.

1. The collision matrix of every frame on the limb points (:mod:`retarget_core.model.collision_geometry`); pairs in
   a hand contact (ctx.constraints) are not collisions: the model never pushes a hand off a contact (the
   optimisation stage brings a sunk hand to the surface).
2. The four limb models on the frames with a non-zero limb row (batched): residual quaternions on the limb joints;
   identity elsewhere (exactly: the model's residual is zero for a zero row).
3. Smooth in time: the residuals (as rotation vectors) are filtered by a 5-tap binomial kernel (the model is
   per-frame, as paper 2's).
4. Never worse: every changed frame is checked with all vertices (:func:`check_frames`, the judged pairs); where
   penetration or a contact got worse the residual is halved (to zero after a few rounds), blended smoothly
   around it; frames still unchecked after the last round go back to the input.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import roma
import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.context import RefineContext, StageOutcome
from retarget_core.geometry.judged_pairs import judged_allowed
from retarget_core.model.collision_geometry import LIMB_ROWS, LimbPoints, collision_matrix, contact_exempt, limb_points
from retarget_core.model.collision_net import (
    BodyRig,
    CollisionNet,
    apply_residuals,
    body_rig,
    load_collision_net,
    pose_features,
    run_model,
)
from retarget_core.motion import Motion
from retarget_core.refine.collision_check import (
    ContactInstances,
    FrameCheck,
    check_frames,
    contact_instances,
    stage_figures,
)
from retarget_core.refine.collision_params import at_fps
from retarget_core.refine.never_worse import FallbackSettings, NeverWorse, run_never_worse

WEIGHTS_PATH = Path(__file__).resolve().parents[1] / "data" / "models" / "collisions.pt"
WEIGHTS_ENV = "RETARGET_COLLISION_WEIGHTS"
"""Environment variable naming other weights for the stage (evaluating a training run before shipping it; not
a job option: a job cannot name a file to load)."""


@dataclass(frozen=True)
class LearnedCollisionParams:
    """Settings of the stage; lengths at a 1.80 m character, frame counts at 30 fps."""

    chunk: int = 256  # frames per batched model call
    smooth: tuple[float, ...] = (1.0, 4.0, 6.0, 4.0, 1.0)  # temporal kernel of the residuals
    penetration_tolerance_m: float = 0.003  # as the metrics: deeper vertices count as penetrating
    worse_volume_fraction: float = 0.02  # a frame is worse when its penetration volume grows by more than 2 % ...
    worse_volume_m3: float = 2e-8  # ... and by more than this
    worse_depth_m: float = 0.002  # or its deepest vertex goes 2 mm deeper
    contact_ok_m: float = 0.02  # a contact closer than this is kept (the judge keeps below 2.5 cm)
    fallback_ramp: int = 8
    fallback_rounds: int = 4
    fallback_factor: float = 0.5
    fallback_floor: float = 0.2
    changed_rad: float = 1e-4


def shipped_collision_net(path: str | None = None, device: str = "cpu") -> CollisionNet:
    """The shipped weights (or those at ``path``, or named by ``$RETARGET_COLLISION_WEIGHTS``) on ``device``,
    loaded once per process."""
    return _load(path or os.environ.get(WEIGHTS_ENV) or str(WEIGHTS_PATH), device)


@lru_cache(maxsize=4)
def _load(path: str, device: str) -> CollisionNet:
    return load_collision_net(path, device)[0]


def _residual_rotvec(model: CollisionNet, rig: BodyRig, lp: LimbPoints, local: Tensor, trans: Tensor, frames: Tensor,
                     m_col: Tensor, chunk: int) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Per joint rotation vectors ``(F, J, 3)`` of the model's residuals at ``frames`` (zero elsewhere), and the
    limb joints ``(K,)`` it may turn."""
    out = torch.zeros(local.shape[0], local.shape[1], 3)
    with torch.no_grad():
        for s in range(0, len(frames), chunk):
            fr = frames[s : s + chunk]
            _, mats, gpos = lp.poser(local[fr], trans[fr])
            dq = run_model(model, pose_features(rig, local[fr], mats, gpos), m_col[fr], rig.shoulder)
            turned = apply_residuals(rig, local[fr], dq)
            delta = local[fr].transpose(-1, -2) @ turned  # (n, J, 3, 3) local residual
            out[fr] = roma.rotmat_to_rotvec(delta)
    joints = torch.cat([j[j >= 0] for j in rig.limb_joints.values()])
    return out, joints


def _smooth(resid: Tensor, kernel: tuple[float, ...]) -> Tensor:
    """``resid (F, J, 3)`` filtered along frames by ``kernel`` (normalised; edges replicated)."""
    k = torch.tensor(kernel) / sum(kernel)
    r = len(kernel) // 2
    x = resid.permute(1, 2, 0).reshape(-1, 1, resid.shape[0])
    x = torch.nn.functional.pad(x, (r, r), mode="replicate")
    y = torch.nn.functional.conv1d(x, k.view(1, 1, -1))
    return y.view(resid.shape[1], 3, resid.shape[0]).permute(2, 0, 1)


def _apply(rot_in: Tensor, joints: Tensor, resid: Tensor) -> Tensor:
    """``rot_in (F, J, 4)`` with ``rot_in[:, j] * exp(resid[:, j])`` for the ``joints``."""
    out = rot_in.clone()
    out[:, joints] = rot.normalize(rot.mul(rot_in[:, joints], roma.rotvec_to_unitquat(resid[:, joints])))
    return out


def resolve_learned(ctx: RefineContext, motion: Motion, params: LearnedCollisionParams | None = None,
                    model: CollisionNet | None = None) -> StageOutcome:  # fmt: skip
    """The learned resolver on ``motion`` (on ``ctx.target``'s skeleton); see the module doc."""
    p = params or LearnedCollisionParams()
    t0 = time.perf_counter()
    model = model or shipped_collision_net()
    ch, sdf, parts = ctx.target, ctx.sdf, ctx.parts
    scale = sdf.scale_to_180
    f_n = motion.num_frames
    rot_in, trans = motion.rotations.float(), motion.translations.float()
    local = roma.unitquat_to_rotmat(rot_in)
    contacts = contact_instances(sdf, ctx.constraints)
    if contacts.count and int(contacts.frame.max()) >= f_n:  # a motion shorter than the context's
        keep = contacts.frame < f_n
        contacts = ContactInstances(contacts.frame[keep], contacts.hand[keep], contacts.cluster[keep])
    cluster = torch.tensor(parts.cluster, dtype=torch.long)
    exempt = contact_exempt(f_n, contacts.frame, cluster[contacts.hand], contacts.cluster)
    lp = limb_points(ch, parts, sdf)
    m_col = collision_matrix(sdf, lp, local, trans, exempt)
    active = torch.nonzero(m_col[:, list(LIMB_ROWS)].flatten(1).amax(-1) > 0).flatten()
    t_model = time.perf_counter()
    resid, joints = _residual_rotvec(model, body_rig(ch, ctx.target_mapping, parts), lp, local, trans, active, m_col, p.chunk)
    model_s = time.perf_counter() - t_model
    resid = _smooth(resid, p.smooth) if len(active) else resid
    tol = p.penetration_tolerance_m / scale
    allowed = judged_allowed(sdf)
    magnitude = resid.norm(dim=-1).amax(-1)  # (F,)
    check_set = torch.nonzero(magnitude > p.changed_rad).flatten()
    before = check_frames(ch, sdf, rot_in, trans, torch.arange(f_n), contacts, tol, allowed=allowed)

    def measure(w: Tensor, frames: Tensor) -> FrameCheck:
        return check_frames(ch, sdf, _apply(rot_in, joints, resid * w[:, None, None]), trans, frames, contacts, tol,
                            allowed=allowed)  # fmt: skip

    fallback = FallbackSettings(p.fallback_rounds, p.fallback_factor, p.fallback_floor,
                                at_fps(p.fallback_ramp, motion.fps))  # fmt: skip
    guard = run_never_worse(NeverWorse.start(before, contacts), check_set, measure, p, scale, fallback)
    final, weight = guard.final, guard.weight
    resid = resid * weight[:, None, None]
    changed = resid.norm(dim=-1).amax(-1) > p.changed_rad
    out_rot = _apply(rot_in, joints, resid)
    out_rot[~changed] = rot_in[~changed]
    angle = torch.rad2deg(resid.norm(dim=-1))
    report: dict[str, Any] = {
        "method": "paper 2 per-limb learned resolver (collision matrix, semantic matrix, dense residual quaternions)",
        "frames_changed": int(changed.sum()), "frames_colliding_input": int(len(active)),
        "fallback_frames": int((weight < 1).sum()),
        "settle_rounds": guard.settle_rounds,
        "mean_joint_change_deg": round(float(angle[changed].mean()) if bool(changed.any()) else 0.0, 3),
        "max_joint_change_deg": round(float(angle.max()) if angle.numel() else 0.0, 2),
        "model_ms_per_frame": round(1000 * model_s / max(len(active), 1), 4),
        "ms_per_frame": round(1000 * (time.perf_counter() - t0) / max(f_n, 1), 3),
        **stage_figures(before, final, contacts, ch.num_vertices, scale),
    }  # fmt: skip
    result = Motion(motion.skeleton, motion.fps, out_rot.to(motion.rotations.dtype), motion.translations.clone(), motion.name)
    return StageOutcome(result, report)


def run(ctx: RefineContext, motion: Motion) -> StageOutcome:
    """The stage entry point (``refine`` registry): :func:`resolve_learned` with the shipped weights."""
    return resolve_learned(ctx, motion)


__all__ = ["LearnedCollisionParams", "WEIGHTS_PATH", "resolve_learned", "run", "shipped_collision_net"]
