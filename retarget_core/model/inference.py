"""Running the shipped network on one job: features from the refinement context, the network's output as a
motion, and the pieces ESO needs (encoder states, target embedding)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch
from torch import Tensor

from retarget_core.context import RefineContext
from retarget_core.model.features import (
    TargetRig,
    apply_residual,
    source_canonical_positions,
    source_features,
    target_rig,
)
from retarget_core.model.network import RecurrentRetargeter, load_network
from retarget_core.model.windowed_decode import DecodeWindows, decode_windows
from retarget_core.motion import Motion

WEIGHTS_PATH = Path(__file__).resolve().parents[1] / "data" / "models" / "recurrent.pt"


_WEIGHTS_OVERRIDE: ContextVar[str | None] = ContextVar("recurrent_weights", default=None)


@contextmanager
def network_weights(path: str | Path | None) -> Iterator[None]:
    """Within the block, the ``recurrent`` and ``eso`` stages use the weights at ``path`` instead of the
    shipped ones (the evaluation's ablation rows; None: the shipped weights). Not a job option: a job cannot
    name a file to load."""
    token = _WEIGHTS_OVERRIDE.set(None if path is None else str(path))
    try:
        yield
    finally:
        _WEIGHTS_OVERRIDE.reset(token)


def shipped_network(device: str = "cpu", path: str | None = None) -> RecurrentRetargeter:
    """The shipped weights (or those at ``path``, or set by :func:`network_weights`) on ``device``, loaded
    once per process."""
    return _load(device, path or _WEIGHTS_OVERRIDE.get() or str(WEIGHTS_PATH))


@lru_cache(maxsize=8)
def _load(device: str, path: str) -> RecurrentRetargeter:
    model, _ = load_network(path, device)
    return model


@dataclass
class NetworkInputs:
    """Inputs of one clip on one target: features ``(1, F, SOURCE_DIM)``, heading ``(1, F, 4)``, the copy
    ``(1, F, J, 4|3)``, the target code ``(1, TARGET_DIM)``, the rig and its geometry points
    ``(1, POINTS, POINT_DIM)`` (read by a "pointnet" network only)."""

    rig: TargetRig
    features: Tensor
    heading: Tensor
    copy_rot: Tensor
    copy_trans: Tensor
    code: Tensor
    points: Tensor | None = None


def network_inputs(ctx: RefineContext, base: Motion | None = None) -> NetworkInputs:
    """Inputs from a refinement context; ``base`` is the motion the residual is added to (default: the copy)."""
    base = base or ctx.before
    rig = target_rig(ctx.target.skeleton, ctx.target_mapping, ctx.target.vertices, ctx.parts)
    sv = ctx.source_view
    src_pos = source_canonical_positions(sv.skeleton, ctx.source_mapping, sv.rotations, sv.translations)
    copy_rot = base.rotations.float()[None].to(ctx.device)
    copy_trans = base.translations.float()[None].to(ctx.device)
    feats, head = source_features(rig, copy_rot, copy_trans, src_pos.float()[None].to(ctx.device), ctx.source_body.height)
    return NetworkInputs(rig, feats, head, copy_rot, copy_trans, rig.code[None].to(ctx.device), rig.points[None].to(ctx.device))


def decode_motion(model: RecurrentRetargeter, inputs: NetworkInputs, states: Tensor, embedding: Tensor,
                  windows: DecodeWindows | None = None) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Local rotations ``(F, J, 4)`` and translations ``(F, J, 3)`` decoded from encoder states ``(1, F, H)``;
    with ``windows``, of its frames ``first .. last - 1`` only (``inputs`` then hold just those frames)."""
    if windows is None:
        rot6, root_offset = model.decode(states, embedding)
    else:
        rot6, root_offset = decode_windows(model, windows, states, embedding)
    r, t = apply_residual(inputs.rig, inputs.copy_rot, inputs.copy_trans, inputs.heading, rot6, root_offset)
    return r[0], t[0]


def run_network(model: RecurrentRetargeter, inputs: NetworkInputs) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The network's output ``(F, J, 4)``, ``(F, J, 3)``, its encoder states ``(1, F, H)`` and the target
    embedding ``(1, E)`` (no gradients)."""
    with torch.no_grad():
        states = model.encode(inputs.features)
        emb = model.embed(inputs.code, inputs.points)
        r, t = decode_motion(model, inputs, states, emb)
    return r, t, states, emb


__all__ = ["WEIGHTS_PATH", "NetworkInputs", "decode_motion", "network_inputs", "network_weights", "run_network", "shipped_network"]
