"""Training of the recurrent retargeter, weakly supervised by the energy (paper 1, appendix B.1), on a small CPU.

Per step: one generated body, ``batch`` windows of ``window`` frames (60, as the paper) drawn from the clips,
their mirrors and the IK contact windows, re-timed by a random speed. Loss per window, averaged:
- skeleton terms against the copy on every frame: rotation identity (rho), root velocity, end-effector
  velocities (omega);
- foot term on every frame, its weight ramped in linearly over the run (paper: current_epoch / epochs);
- interpenetration on ``geometry_frames`` random frames per window, every vertex skinned (the grids are per
  segment, so the SDF query needs the full mesh; sampling frames is what bounds the cost);
- vertex contact on every frame with constraints (only the constrained vertices are skinned: cheap).
Adam (beta1 0.5), dropout 0.1, lr decayed per "epoch" (``steps_per_epoch``). Seeded: the same settings and
seed give the same weights (single-threaded). Losses go to a JSON-lines log.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from retarget_core.bodies.params import BodyParams
from retarget_core.energy.sdf import REFERENCE_HEIGHT_M
from retarget_core.kinematics import forward_kinematics
from retarget_core.model import energy as en
from retarget_core.model.data import Dataset, build_dataset, draw_windows, load_body_kit, training_clips
from retarget_core.model.features import apply_residual, source_features
from retarget_core.model.network import NetworkConfig, RecurrentRetargeter, save_network
from retarget_core.model.training_log import TrainingLog

log = logging.getLogger(__name__)

# Stratified bank: weight and muscle spread from thin to heavy so that heavy and bulky bodies are seen; the
# other parameters (gender, age, height, proportions) are drawn by sample_body_params.
BODY_WEIGHT_MUSCLE: tuple[tuple[float, float], ...] = (
    (0.15, 0.3), (0.5, 0.5), (0.95, 0.9), (0.35, 0.8), (0.75, 0.4), (1.0, 1.0),
)  # fmt: skip


@dataclass
class TrainConfig:
    """Settings of one training run (all recorded in the weights' meta)."""

    seed: int = 0
    bodies: int = 6
    ik_windows: int = 80
    ik_length: int = 60
    window: int = 60
    batch: int = 8
    geometry_frames: int = 1  # paper: one random frame per sequence
    ik_share: float = 0.3  # share of windows drawn from the IK contact windows
    speed_range: tuple[float, float] = (0.8, 1.25)
    steps: int = 1500
    max_minutes: float = 30.0
    steps_per_epoch: int = 150
    learning_rate: float = 1e-3  # paper 1e-4 with batches of 256 and 10 epochs on a GPU; we take far fewer steps
    lr_decay_per_epoch: float = 0.95
    adam_betas: tuple[float, float] = (0.5, 0.999)
    # Energy weights. The paper's (contact 1000, interpenetration 100, foot 0.1, rotation 1000, ee 1000) are for
    # its own term definitions; ours (energy/terms.py) make a 5 degree joint change cost as much as a hand
    # 1 cm deep over 3 cm^2 at rotation 100, which is the balance we want: skeleton terms 10x lower than the
    # paper relative to the geometry terms.
    w_contact: float = 1000.0
    w_interpenetration: float = 100.0
    w_foot: float = 0.1
    w_rotation: float = 100.0
    w_root: float = 100.0
    w_end_effector: float = 100.0
    w_root_offset: float = 10.0  # the root offset itself (m^2 at 1.80 m): 3 cm costs as much as about 1 degree
    energy: str = "full"  # which ablation of ENERGY_TERMS the weights above are (set by with_energy)
    network: NetworkConfig = field(default_factory=NetworkConfig)


ENERGY_TERMS: dict[str, tuple[str, ...]] = {
    "skeleton": ("w_foot", "w_interpenetration", "w_contact"),
    "foot": ("w_interpenetration", "w_contact"),
    "interpenetration": ("w_contact",),
    "full": (),
}
"""Paper 1 table 3's ablation: energy name -> the weights set to 0 (skeleton terms only; + foot;
+ interpenetration; the full energy with vertex contacts)."""


def with_energy(cfg: TrainConfig, energy: str) -> TrainConfig:
    """``cfg`` trained on the energy ``energy`` (a key of :data:`ENERGY_TERMS`): the other terms weighted 0."""
    if energy not in ENERGY_TERMS:
        raise ValueError(f"unknown energy {energy!r}; one of {', '.join(ENERGY_TERMS)}")
    zeroed: dict[str, Any] = {w: 0.0 for w in ENERGY_TERMS[energy]}
    return replace(cfg, energy=energy, **zeroed)


def body_bank(seed: int, count: int) -> list[BodyParams]:
    """``count`` generated bodies (gender, age, height, proportions sampled; weight and muscle stratified), each
    away from the held-out bodies (redrawn while :func:`retarget_core.heldout.near_heldout_body`)."""
    from retarget_core.heldout import MAX_REJECTIONS, near_heldout_body, sample_training_body_params

    rng = np.random.default_rng(seed + 1000)
    out = []
    for k in range(count):
        w, m = BODY_WEIGHT_MUSCLE[k % len(BODY_WEIGHT_MUSCLE)]
        for _ in range(MAX_REJECTIONS):
            p = sample_training_body_params(rng, name=f"train_{k}").model_copy(update={"weight": w, "muscle": m})
            if not near_heldout_body(p):
                break
        else:
            raise RuntimeError(f"no training body {k} away from the held-out bodies")
        out.append(p)
    return out


def dataset_key(clips: list[Path], bodies: list[BodyParams], cfg: TrainConfig) -> str:
    blob = json.dumps([[p.stem for p in clips], [b.model_dump() for b in bodies], cfg.ik_windows, cfg.ik_length, cfg.seed])
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def get_dataset(clip_dir: Path, cfg: TrainConfig, cache_dir: Path) -> Dataset:
    """The training set, from ``cache_dir`` when built before with the same settings."""
    clips = training_clips(clip_dir)
    bodies = body_bank(cfg.seed, cfg.bodies)
    path = cache_dir / f"recurrent-data-{dataset_key(clips, bodies, cfg)}.pt"
    if path.is_file():
        data: Dataset = torch.load(path, weights_only=False)
        return data
    data = build_dataset(clips, bodies, cfg.ik_windows, cfg.ik_length, cfg.seed)
    cache_dir.mkdir(parents=True, exist_ok=True)
    torch.save(data, path)
    return data


def window_loss(
    model: RecurrentRetargeter, kit: en.BodyKit, batch: Any, cfg: TrainConfig, foot_ramp: float, rng: np.random.Generator
) -> tuple[torch.Tensor, dict[str, float]]:
    """The weighted energy of the network's output on one batch of windows, and each term's mean."""
    rig = kit.rig
    feats, head = source_features(rig, batch.copy_rot, batch.copy_trans, batch.source_pos, batch.source_height[:, None, None, None])
    code = rig.code[None].expand(feats.shape[0], -1)
    rot6, root_offset = model(feats, code, rig.points[None])
    new_rot, new_trans = apply_residual(rig, batch.copy_rot, batch.copy_trans, head, rot6, root_offset)
    b_n, t_n = new_rot.shape[:2]
    grot, gpos = forward_kinematics(rig.skeleton.parents, new_rot, new_trans)
    with torch.no_grad():
        _, ref_pos = forward_kinematics(rig.skeleton.parents, batch.copy_rot, batch.copy_trans)
    terms: dict[str, torch.Tensor] = {k: new_rot.new_zeros(()) for k in ("rotation", "root", "end_effector", "foot")}
    for b in range(b_n):
        sk = en.skeleton_terms(kit, new_rot[b], batch.copy_rot[b], gpos[b], ref_pos[b])
        for k, v in sk.items():
            terms[k] = terms[k] + v.mean() / b_n
        terms["foot"] = terms["foot"] + en.feet(kit, gpos[b], batch.feet[b]).mean() / b_n
    root_shift = (new_trans[..., rig.root, :] - batch.copy_trans[..., rig.root, :]) * (REFERENCE_HEIGHT_M / kit.height)
    terms["root_offset"] = root_shift.pow(2).sum(-1).mean()
    frames = torch.from_numpy(rng.integers(0, t_n, size=(b_n, cfg.geometry_frames))).long()
    rows = (torch.arange(b_n)[:, None] * t_n + frames).reshape(-1)
    flat_r, flat_p = grot.reshape(b_n * t_n, *grot.shape[2:]), gpos.reshape(b_n * t_n, *gpos.shape[2:])
    zero = new_rot.new_zeros(())
    # Terms weighted 0 (an ablation, see ENERGY_TERMS) are not computed: they cost most of a step.
    terms["interpenetration"] = en.interpenetration(kit, flat_r[rows], flat_p[rows]).mean() if cfg.w_interpenetration else zero
    if batch.contact_i.numel() and cfg.w_contact:
        d2 = en.contact_distance2(kit, flat_r, flat_p, batch.contact_batch * t_n + batch.contact_frame, batch.contact_i, batch.contact_j)
        terms["contact"] = d2.mean()
    else:
        terms["contact"] = new_rot.new_zeros(())
    weights = {"rotation": cfg.w_rotation, "root": cfg.w_root, "end_effector": cfg.w_end_effector,
               "foot": cfg.w_foot * foot_ramp, "root_offset": cfg.w_root_offset, "interpenetration": cfg.w_interpenetration, "contact": cfg.w_contact}  # fmt: skip
    total = sum(weights[k] * v for k, v in terms.items())
    assert isinstance(total, torch.Tensor)
    return total, {k: float(v.detach()) for k, v in terms.items()}


def fit_normalisation(model: RecurrentRetargeter, data: Dataset, kits: list[en.BodyKit], cfg: TrainConfig, rng: np.random.Generator) -> None:
    """Feature means and deviations from a few batches on every body."""
    src, tgt = [], []
    for b, kit in enumerate(kits):
        for _ in range(4):
            wb = draw_windows(data, b, cfg.batch, cfg.window, rng, cfg.ik_share, cfg.speed_range)
            f, _ = source_features(kit.rig, wb.copy_rot, wb.copy_trans, wb.source_pos, wb.source_height[:, None, None, None])
            src.append(f.reshape(-1, f.shape[-1]))
        tgt.append(kit.rig.code)
    model.set_normalisation(torch.cat(src), torch.stack(tgt))


def train(
    clip_dir: Path, out: Path, cfg: TrainConfig, cache_dir: Path, log_path: Path | None = None, data: Dataset | None = None
) -> dict[str, Any]:
    """Train and save the weights to ``out``; returns the run's summary (also stored in the weights' meta)."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    t_data = time.perf_counter()
    data = data or get_dataset(clip_dir, cfg, cache_dir)
    kits = [load_body_kit(b.params) for b in data.bodies]
    data_seconds = time.perf_counter() - t_data
    model = RecurrentRetargeter(cfg.network)
    fit_normalisation(model, data, kits, cfg, rng)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate, betas=cfg.adam_betas)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.steps_per_epoch, gamma=cfg.lr_decay_per_epoch)
    with TrainingLog(log_path, cfg.max_minutes) as record:
        model.train()
        step = 0
        for step in range(1, cfg.steps + 1):
            body = (step - 1) % len(kits)
            wb = draw_windows(data, body, cfg.batch, cfg.window, rng, cfg.ik_share, cfg.speed_range)
            loss, terms = window_loss(model, kits[body], wb, cfg, min(1.0, step / cfg.steps), rng)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            sched.step()
            last = record.record(step, body, float(loss.detach()), terms, float(sched.get_last_lr()[0]))
            if step % 50 == 0:
                log.info("step %d loss %.4f (ema %.4f) %.0f s", step, last["loss"], record.ema["loss"], last["seconds"])
            if record.out_of_time():
                log.info("time budget reached at step %d", step)
                break
        train_seconds = record.seconds
    model.eval()
    summary = {
        "steps": step, "train_seconds": round(train_seconds, 1), "data_seconds": round(data_seconds, 1),
        "final": record.last, "ema": record.ema, "config": _jsonable(asdict(cfg)), "data": data.info,
        "bodies": [b.params.model_dump() for b in data.bodies], "torch_threads": torch.get_num_threads(),
    }  # fmt: skip
    save_network(model, out, summary)
    return summary


def _jsonable(x: Any) -> Any:
    return json.loads(json.dumps(x, default=str))


__all__ = ["BODY_WEIGHT_MUSCLE", "ENERGY_TERMS", "TrainConfig", "body_bank", "get_dataset", "train", "window_loss", "with_energy"]
