"""Training of paper 2's per-limb collision resolver (sections 5.2 and 6) on copy poses of generated bodies.

Per step: one body of the bank, ``batch`` frames (a share ``colliding_share`` drawn among frames whose input
collision matrix has a limb row non-zero). Per frame:

- random segment padding (RSP, eq. 14): with probability ``pad_prob`` every segment gets a padding drawn in
  ``pad_range`` (at 1.80 m), applied to the distances of the collision matrix and to the box extents;
- random collision dropout (RCD, eq. 13): with probability ``dropout`` (0.5) only one non-zero element of the
  limb rows of ``M_col`` is kept;
- losses (eq. 9): identity (eq. 10; zero by construction here, see :mod:`collision_net`), penetration (eq. 11/13:
  ``M_col`` of the output where the (dropped-out) input collides; our addition: also where the input did not
  collide at all, so resolving one collision by making another is not free), reconstruction (eq. 12: local
  quaternions, FK positions and FK rotations, positions over the shoulder height), L2 on the weights.

Weights: identity 10, reconstruction 0.3 as paper 2; penetration 2.0 (paper 0.5) and L2 1e-6 (paper 1e-5), see
:class:`CollisionTrainConfig`; lengths in shoulder heights.
Adam; the step size decays by cosine from ``learning_rate`` to a tenth. Seeded: the same settings and seed give
the same weights (single-threaded). Losses go to a JSON-lines log.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import roma
import torch
from torch import Tensor

from retarget_core.model.collision_data import BodyFrames, BodyKitC, CollisionData, body_kit_c, get_collision_data
from retarget_core.model.collision_geometry import LIMB_ROWS, cluster_depths, find_triples
from retarget_core.model.collision_net import (
    CollisionNet,
    CollisionNetConfig,
    LimbResolver,
    apply_residuals,
    pose_features,
    run_model,
    save_collision_net,
)
from retarget_core.model.train_recurrent import body_bank
from retarget_core.model.training_log import TrainingLog

log = logging.getLogger(__name__)


@dataclass
class CollisionTrainConfig:
    """Settings of one training run (recorded in the weights' meta)."""

    seed: int = 0
    bodies: int = 12
    stride: int = 2  # every 2nd frame of the 30 fps clips
    batch: int = 32  # paper 2
    steps: int = 8000
    max_minutes: float = 18.0
    learning_rate: float = 1e-3  # paper 1e-4 for far more steps on a GPU
    colliding_share: float = 0.85
    dropout: float = 0.5  # RCD probability (paper 2: lambda = 0.5)
    pad_prob: float = 0.7  # share of frames with random segment padding (paper: all)
    pad_range_m: tuple[float, float] = (-0.015, 0.025)  # at 1.80 m (paper: up to 0.1 shoulder heights)
    slack_m: float = 0.06  # triples taken within this of a segment on the input (covers padding and the move)
    w_identity: float = 10.0
    w_penetration: float = 2.0  # paper 0.5 leaves the model too conservative (docs/model-collisions.md)
    w_reconstruction: float = 0.3
    w_l2: float = 1e-6  # paper 1e-5, too heavy against our losses in shoulder heights (small)
    network: CollisionNetConfig = field(default_factory=CollisionNetConfig)


def draw_frames(frames: BodyFrames, batch: int, share: float, rng: np.random.Generator) -> Tensor:
    """``(batch,)`` frame indices: a share ``share`` among the colliding frames, the rest uniform."""
    coll = torch.nonzero(frames.colliding).flatten()
    n = len(frames.rot)
    k = int(round(batch * share)) if len(coll) else 0
    a = coll[torch.from_numpy(rng.integers(0, max(len(coll), 1), size=k))] if k else torch.zeros(0, dtype=torch.long)
    b = torch.from_numpy(rng.integers(0, n, size=batch - k))
    return torch.cat([a, b]).long()


def dropout_mask(m_in: Tensor, prob: float, gen: torch.Generator) -> Tensor:
    """RCD: ``(B, 6, 6)`` mask; on a share ``prob`` of the frames only one random non-zero limb-row element is 1."""
    b_n = m_in.shape[0]
    rows = list(LIMB_ROWS)
    limb = m_in[:, rows].flatten(1)  # (B, 24)
    score = torch.rand(limb.shape, generator=gen) * (limb > 0)
    one = torch.zeros_like(limb).scatter_(1, score.argmax(1, keepdim=True), 1.0)
    drop = (torch.rand(b_n, generator=gen) < prob) & (limb > 0).any(1)
    mask = torch.ones_like(m_in)
    mask[:, rows] = torch.where(drop[:, None], one, torch.ones_like(one)).view(b_n, len(rows), -1)
    return mask


def step_loss(model: CollisionNet, kit: BodyKitC, frames: BodyFrames, idx: Tensor, cfg: CollisionTrainConfig,
              gen: torch.Generator) -> tuple[Tensor, dict[str, float]]:  # fmt: skip
    """The weighted loss of one batch of frames ``idx`` of one body, and each term's value."""
    rig, sdf, lp = kit.rig, kit.sdf, kit.points
    local = roma.unitquat_to_rotmat(frames.rot[idx])
    trans = frames.trans[idx]
    exempt = frames.exempt[idx]
    b_n, s_n = len(idx), kit.parts.num_parts
    lo, hi = (v / lp.scale for v in cfg.pad_range_m)
    pad = lo + (hi - lo) * torch.rand(b_n, s_n, generator=gen)
    pad = pad * (torch.rand(b_n, 1, generator=gen) < cfg.pad_prob)
    with torch.no_grad():
        posed, mats, gpos = lp.poser(local, trans)
        triples = find_triples(sdf, lp, posed, mats, cfg.slack_m)
        m_in = cluster_depths(sdf, lp, triples, posed, mats, pad, exempt)
        m_feed = m_in * dropout_mask(m_in, cfg.dropout, gen)
    feats = pose_features(rig, local, mats, gpos, pad)
    dq = run_model(model, feats, m_feed, rig.shoulder)
    local_hat = apply_residuals(rig, local, dq)
    posed_h, mats_h, gpos_h = lp.poser(local_hat, trans)
    m_out = cluster_depths(sdf, lp, triples, posed_h, mats_h, pad, exempt)
    rows = list(LIMB_ROWS)
    watched = ((m_feed > 0) | (m_in <= 0)).float()
    pen = (m_out[:, rows] * watched[:, rows]).sum((1, 2)).mean() / rig.shoulder
    zero = {c: model.limbs[c](feats[c], torch.zeros(b_n, 6)) for c in dq}
    identity = sum((z.norm(dim=-1).mean() for z in zero.values()), torch.zeros(()))
    e = torch.tensor([0.0, 0.0, 0.0, 1.0])
    q_term = torch.stack([((d + e) / (d + e).norm(dim=-1, keepdim=True) - e).norm(dim=-1).mean() for d in dq.values()]).mean()
    p_term = (gpos_h - gpos).norm(dim=-1).mean() / rig.shoulder
    r_term = (mats_h[..., :3] - mats[..., :3]).flatten(-2).norm(dim=-1).mean() / 2.0
    recon = q_term + p_term + r_term
    l2 = sum((p.pow(2).sum() for n, p in model.named_parameters() if "weight" in n), torch.zeros(()))
    total = cfg.w_identity * identity + cfg.w_penetration * pen + cfg.w_reconstruction * recon + cfg.w_l2 * l2
    with torch.no_grad():
        in_pen = (m_in[:, rows] * watched[:, rows]).sum((1, 2)).mean() / rig.shoulder
    terms = {k: float(v.detach()) for k, v in (("identity", identity), ("penetration", pen), ("penetration_input", in_pen),
                                                 ("reconstruction", recon), ("l2", l2))}  # fmt: skip
    return total, terms


def fit_normalisation(model: CollisionNet, data: CollisionData, kits: list[BodyKitC], rng: np.random.Generator) -> None:
    """Feature means and deviations from up to 256 frames of every body."""
    feats: dict[str, list[Tensor]] = {c: [] for c in model.limbs}
    for frames, kit in zip(data.bodies, kits, strict=True):
        idx = torch.from_numpy(rng.integers(0, len(frames.rot), size=min(256, len(frames.rot)))).long()
        with torch.no_grad():
            local = roma.unitquat_to_rotmat(frames.rot[idx])
            _, mats, gpos = kit.points.poser(local, frames.trans[idx])
            for c, f in pose_features(kit.rig, local, mats, gpos).items():
                feats[c].append(f)
    for c, fs in feats.items():
        x = torch.cat(fs)
        limb = model.limbs[c]
        assert isinstance(limb, LimbResolver)
        limb.mean.copy_(x.mean(0))
        limb.std.copy_(x.std(0).clamp_min(1e-3))


def train_collisions(clip_dir: Path, out: Path, cfg: CollisionTrainConfig, cache_dir: Path, log_path: Path | None = None,
                     data: CollisionData | None = None) -> dict[str, Any]:  # fmt: skip
    """Train and save the weights to ``out``; returns the run's summary (also stored in the weights' meta)."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    t_data = time.perf_counter()
    data = data or get_collision_data(clip_dir, body_bank(cfg.seed, cfg.bodies), cfg.stride, cfg.seed, cache_dir)
    kits = [body_kit_c(b.params) for b in data.bodies]
    data_seconds = time.perf_counter() - t_data
    model = CollisionNet(cfg.network)
    fit_normalisation(model, data, kits, rng)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate)
    with TrainingLog(log_path, cfg.max_minutes) as record:
        model.train()
        step = 0
        for step in range(1, cfg.steps + 1):
            frac = (step - 1) / max(cfg.steps - 1, 1)
            for g in opt.param_groups:
                g["lr"] = cfg.learning_rate * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * frac)))
            body = (step - 1) % len(kits)
            idx = draw_frames(data.bodies[body], cfg.batch, cfg.colliding_share, rng)
            loss, terms = step_loss(model, kits[body], data.bodies[body], idx, cfg, gen)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            last = record.record(step, body, float(loss.detach()), terms, opt.param_groups[0]["lr"])
            ema = record.ema
            if step % 100 == 0:
                log.info("step %d loss %.5f pen %.5f / input %.5f (ema) %.0f s", step, ema["loss"], ema["penetration"],
                         ema["penetration_input"], last["seconds"])  # fmt: skip
            if record.out_of_time():
                log.info("time budget reached at step %d", step)
                break
        train_seconds = record.seconds
    model.eval()
    summary = {
        "steps": step, "train_seconds": round(train_seconds, 1), "data_seconds": round(data_seconds, 1),
        "final": record.last, "ema": record.ema, "config": json.loads(json.dumps(asdict(cfg), default=str)), "data": data.info,
        "bodies": [b.params.model_dump() for b in data.bodies], "torch_threads": torch.get_num_threads(),
    }  # fmt: skip
    save_collision_net(model, out, summary)
    return summary


__all__ = ["CollisionTrainConfig", "draw_frames", "dropout_mask", "fit_normalisation", "step_loss", "train_collisions"]
