"""Refinement stage ``recurrent``: the geometry-conditioned network (retarget_core.model) adds its residual
rotations and root motion to the motion so far (normally the copy baseline)."""

from __future__ import annotations

import math
import time

import torch

from retarget_core.context import RefineContext, StageOutcome
from retarget_core.model.inference import network_inputs, run_network, shipped_network
from retarget_core.motion import Motion

CHANGED_DEGREES = 0.5  # a frame counts as changed when a joint turned by more than this
CHANGED_ROOT_M = 0.005  # ... or the root moved by more than this (at 1.80 m)


def run(ctx: RefineContext, motion: Motion) -> StageOutcome:
    """The network's output on ``motion``; the report gives frames changed, mean and largest joint change and
    the time per frame."""
    start = time.perf_counter()
    model = shipped_network(str(ctx.device))
    inputs = network_inputs(ctx, motion)
    rot, trans, _, _ = run_network(model, inputs)
    rot, trans = rot.cpu().to(motion.rotations.dtype), trans.cpu().to(motion.translations.dtype)
    out = Motion(motion.skeleton, motion.fps, rot, trans, motion.name)
    dot = (rot * motion.rotations).sum(-1).abs().clamp(max=1.0)
    angle = torch.rad2deg(2 * torch.acos(dot))  # (F, J)
    root_move = (trans[:, inputs.rig.root] - motion.translations[:, inputs.rig.root]).norm(dim=-1) * 1.80 / ctx.target.height
    changed = (angle.amax(-1) > CHANGED_DEGREES) | (root_move > CHANGED_ROOT_M)
    seconds = time.perf_counter() - start
    return StageOutcome(out, {
        "frames_changed": int(changed.sum()),
        "mean_joint_change_deg": round(float(angle.mean()), 3),
        "max_joint_change_deg": round(float(angle.max()), 2) if angle.numel() else 0.0,
        "max_root_change_cm_at_180": round(float(root_move.max()) * 100, 2) if root_move.numel() else 0.0,
        "ms_per_frame": round(1000 * seconds / max(motion.num_frames, 1), 3),
        "device": str(ctx.device),
        "finite": bool(math.isfinite(float(rot.sum()))),
    })  # fmt: skip


__all__ = ["run"]
