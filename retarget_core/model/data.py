"""Training data of the recurrent retargeter: the shared CMU clips (not the held-out ones), mirrored, plus
contact-rich windows made by IK (:mod:`retarget_core.model.augment`), on generated bodies.

Per source sequence (a clip, its mirror, or an IK window) we keep what does not depend on the target: the
source's canonical joint positions on its own body, its foot labels and its hand contacts (source vertex
pairs). Per (sequence, target body) the copy baseline. Everything is built once and cached in one file
(:func:`build_dataset`); re-timing happens when windows are drawn (:func:`draw_windows`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.bodies.params import BodyParams
from retarget_core.body_cache import body_assets
from retarget_core.canonical import CANONICAL_JOINTS, JointMapping, mirror
from retarget_core.character import Character
from retarget_core.contacts.correspondence import build_correspondence
from retarget_core.copy_retarget import copy_retarget
from retarget_core.heldout import heldout_clip_names, training_clip_paths
from retarget_core.kinematics import global_to_local
from retarget_core.mapping import map_joints
from retarget_core.measure import detect_source_contacts
from retarget_core.model.augment import contact_window
from retarget_core.model.energy import BodyKit, body_kit
from retarget_core.model.features import source_canonical_positions
from retarget_core.motion import Motion

log = logging.getLogger(__name__)

HELD_OUT_CLIPS: tuple[str, ...] = ("002_03", "005_10", "006_08", "007_05")
"""Clips kept out of training besides the fixed held-out split (``retarget_core/data/heldout.json``, see
:mod:`retarget_core.heldout`): the four that ``benchmarks/eval/recurrent_eval.py`` evaluates on. The shared
``mh_*`` bodies are held out too: training bodies are generated
(:func:`retarget_core.heldout.sample_training_body_params`)."""
TRAIN_FPS = 30.0
MAX_CLIP_FRAMES = 600  # 20 s per clip at most: long clips would dominate the windows drawn
FOOT_MIRROR = (2, 3, 0, 1)  # (left toe, left heel, right toe, right heel) swapped


@dataclass
class SourceSequence:
    """One source sequence on its source body (all ``F`` frames at 30 fps).

    motion: on the source body's 22-joint skeleton; canonical_pos: ``(F, 22, 3)``; height: the source body's;
    feet: ``(F, 4)`` bool; contact_frame/i/j: ``(M,)`` source-body vertex pairs in contact; kind: clip,
    mirror or ik."""

    name: str
    kind: str
    motion: Motion
    canonical_pos: Tensor
    height: float
    feet: Tensor
    contact_frame: Tensor
    contact_i: Tensor
    contact_j: Tensor


@dataclass
class BodyCopies:
    """Per training body: its parameters and, per sequence, the copy baseline and the contacts as target
    vertex pairs."""

    params: BodyParams
    copy_rot: list[Tensor] = field(default_factory=list)
    copy_trans: list[Tensor] = field(default_factory=list)
    pair_i: list[Tensor] = field(default_factory=list)
    pair_j: list[Tensor] = field(default_factory=list)


@dataclass
class Dataset:
    sequences: list[SourceSequence]
    bodies: list[BodyCopies]
    source_params: BodyParams
    info: dict[str, object]


def mirror_motion(motion: Motion, mapping: JointMapping) -> Motion:
    """The motion reflected across the body's sagittal plane (x -> -x), left and right swapped; for a
    left-right symmetric rig (the built-in bodies)."""
    grot, gpos = motion.global_transforms()
    swap = list(range(motion.skeleton.num_joints))
    for c in CANONICAL_JOINTS:
        if c in mapping.joints and mirror(c) in mapping.joints:
            swap[mapping.joints[c]] = mapping.joints[mirror(c)]
    sign = torch.tensor([1.0, -1.0, -1.0, 1.0])
    mrot = grot[:, swap] * sign
    mpos = gpos[:, swap] * torch.tensor([-1.0, 1.0, 1.0])
    local_r, local_t = global_to_local(motion.skeleton.parents, rot.normalize(mrot), mpos)
    return Motion(motion.skeleton, motion.fps, local_r, local_t, motion.name + "~mirror")


def vertex_mirror_map(body: Character) -> Tensor:
    """For every vertex, the nearest vertex of the x-reflected rest mesh ``(V,)``."""
    v = body.vertices.detach().numpy()
    _, idx = cKDTree(v).query(v * np.array([-1.0, 1.0, 1.0]), k=1)
    return torch.from_numpy(np.asarray(idx, dtype=np.int64))


def _sequence(name: str, kind: str, body: Character, mapping: JointMapping, motion: Motion) -> SourceSequence:
    found = detect_source_contacts(body, mapping, motion)
    frame, i, j = found.self_contacts.vertex_pairs()
    pos = source_canonical_positions(motion.skeleton, mapping, motion.rotations, motion.translations)
    return SourceSequence(name, kind, motion, pos, body.height, found.feet.labels, frame, i, j)


def _mirrored(seq: SourceSequence, mapping: JointMapping, vmap: Tensor) -> SourceSequence:
    m = mirror_motion(seq.motion, mapping)
    pos = source_canonical_positions(m.skeleton, mapping, m.rotations, m.translations)
    return SourceSequence(seq.name + "~mirror", "mirror", m, pos, seq.height, seq.feet[:, list(FOOT_MIRROR)],
                          seq.contact_frame, vmap[seq.contact_i], vmap[seq.contact_j])  # fmt: skip


def build_dataset(
    clips: list[Path], body_params: list[BodyParams], ik_windows: int, ik_length: int, seed: int,
    max_clip_frames: int = MAX_CLIP_FRAMES,
) -> Dataset:
    """Load the clips onto one neutral source body, mirror them, add ``ik_windows`` IK contact windows of
    ``ik_length`` frames, and make the copy baseline of every sequence on every body."""
    from retarget_core.bodies.makehuman import make_body
    from retarget_core.body_parts import body_parts
    from retarget_core.loading import load_motion
    from retarget_core.resample import resample

    rng = np.random.default_rng(seed)
    src_params = BodyParams(name="source_body", gender=0.5, weight=0.5, muscle=0.5, height=1.75)
    src_body = make_body(src_params)
    src_map = map_joints(src_body.skeleton)
    src_parts = body_parts(src_body, src_map)
    vmap = vertex_mirror_map(src_body)
    seqs: list[SourceSequence] = []
    t0 = time.perf_counter()
    for path in clips:
        lm = load_motion(path)
        m = resample(lm.motion, TRAIN_FPS).slice(0, max_clip_frames)
        view = copy_retarget(m, lm.mapping, src_body.skeleton, src_map)
        view.name = path.stem
        seq = _sequence(path.stem, "clip", src_body, src_map, view)
        seqs.append(seq)
        seqs.append(_mirrored(seq, src_map, vmap))
        log.info("clip %s: %d frames, %d contact pairs (%.0f s)", path.stem, view.num_frames, seq.contact_i.numel(),
                 time.perf_counter() - t0)  # fmt: skip
    clip_seqs = [s for s in seqs if s.kind in ("clip", "mirror") and s.motion.num_frames > ik_length + 1]
    made = 0
    while made < ik_windows:
        base = clip_seqs[int(rng.integers(len(clip_seqs)))]
        start = int(rng.integers(base.motion.num_frames - ik_length))
        win = contact_window(src_body, src_map, src_parts, base.motion, rng, start, ik_length)
        if win is None:
            continue
        seqs.append(_sequence(win.motion.name, "ik", src_body, src_map, win.motion))
        made += 1
    log.info("%d IK windows (%.0f s)", made, time.perf_counter() - t0)
    bodies: list[BodyCopies] = []
    for params in body_params:
        target = make_body(params)
        t_map = map_joints(target.skeleton)
        corr = build_correspondence(src_body, src_map, target, t_map)
        copies = BodyCopies(params)
        for seq in seqs:
            c = copy_retarget(seq.motion, src_map, target.skeleton, t_map)
            copies.copy_rot.append(c.rotations.float())
            copies.copy_trans.append(c.translations.float())
            copies.pair_i.append(corr.map(seq.contact_i))
            copies.pair_j.append(corr.map(seq.contact_j))
        bodies.append(copies)
        body_assets(target, t_map)  # fill the disk cache of parts and SDF grids now
        log.info("body %s done (%.0f s)", params.name, time.perf_counter() - t0)
    info = {
        "clips": [p.stem for p in clips], "held_out_clips": sorted({*HELD_OUT_CLIPS, *heldout_clip_names()}), "ik_windows": ik_windows,
        "ik_length": ik_length, "frames": {k: sum(s.motion.num_frames for s in seqs if s.kind == k) for k in ("clip", "mirror", "ik")},
        "contact_frames": {k: sum(int(s.contact_frame.unique().numel()) for s in seqs if s.kind == k) for k in ("clip", "mirror", "ik")},
        "build_seconds": round(time.perf_counter() - t0, 1),
    }  # fmt: skip
    return Dataset(seqs, bodies, src_params, info)


def training_clips(folder: Path) -> list[Path]:
    """The CMU clips of ``folder`` that training may use: not in the held-out split, not in
    :data:`HELD_OUT_CLIPS`; sorted."""
    return [p for p in training_clip_paths(folder) if p.stem not in HELD_OUT_CLIPS]


def load_body_kit(params: BodyParams) -> BodyKit:
    """The :class:`BodyKit` of a generated body (parts and SDF from the body cache)."""
    from retarget_core.bodies.makehuman import make_body

    target = make_body(params)
    t_map = map_joints(target.skeleton)
    assets, _ = body_assets(target, t_map)
    return body_kit(target, t_map, assets.parts, assets.sdf)


@dataclass
class WindowBatch:
    """``B`` windows of ``T`` frames on one body. copy_rot/trans ``(B, T, J, 4|3)``; source_pos ``(B, T, 22, 3)``;
    source_height ``(B,)``; feet ``(B, T, 4)``; contacts: batch index, frame, i, j ``(M,)`` each."""

    copy_rot: Tensor
    copy_trans: Tensor
    source_pos: Tensor
    source_height: Tensor
    feet: Tensor
    contact_batch: Tensor
    contact_frame: Tensor
    contact_i: Tensor
    contact_j: Tensor


def draw_windows(
    data: Dataset, body: int, batch: int, frames: int, rng: np.random.Generator, ik_share: float,
    speed_range: tuple[float, float],
) -> WindowBatch:  # fmt: skip
    """``batch`` random windows of ``frames`` frames on body ``body``, a share ``ik_share`` from the IK contact
    windows, each re-timed by a random speed (nearest source frame; contacts and labels follow the frames)."""
    copies = data.bodies[body]
    ik = [k for k, s in enumerate(data.sequences) if s.kind == "ik"]
    other = [k for k, s in enumerate(data.sequences) if s.kind != "ik" and s.motion.num_frames >= frames * speed_range[1] + 1]
    rows: dict[str, list[Tensor]] = {k: [] for k in ("rot", "trans", "pos", "h", "feet", "cb", "cf", "ci", "cj")}
    for b in range(batch):
        pool = ik if (ik and rng.random() < ik_share) else other
        k = pool[int(rng.integers(len(pool)))]
        seq = data.sequences[k]
        n = seq.motion.num_frames
        speed = float(rng.uniform(*speed_range))
        span = min(n - 1, int(np.ceil((frames - 1) * speed)))
        speed = min(speed, span / max(frames - 1, 1))
        start = int(rng.integers(0, n - span)) if n - span > 0 else 0
        idx = torch.from_numpy(np.clip(np.round(start + np.arange(frames) * speed), 0, n - 1).astype(np.int64))
        rows["rot"].append(copies.copy_rot[k][idx])
        rows["trans"].append(copies.copy_trans[k][idx])
        rows["pos"].append(seq.canonical_pos[idx].float())
        rows["h"].append(torch.tensor(seq.height))
        rows["feet"].append(seq.feet[idx])
        # Contacts: a window frame takes the contacts of the source frame it shows.
        where = torch.full((n,), -1, dtype=torch.long)
        where[idx] = torch.arange(frames)
        f_win = where[seq.contact_frame] if seq.contact_frame.numel() else seq.contact_frame
        keep = f_win >= 0
        rows["cb"].append(torch.full((int(keep.sum()),), b, dtype=torch.long))
        rows["cf"].append(f_win[keep])
        rows["ci"].append(copies.pair_i[k][keep])
        rows["cj"].append(copies.pair_j[k][keep])
    return WindowBatch(
        torch.stack(rows["rot"]), torch.stack(rows["trans"]), torch.stack(rows["pos"]), torch.stack(rows["h"]).float(),
        torch.stack(rows["feet"]), torch.cat(rows["cb"]), torch.cat(rows["cf"]), torch.cat(rows["ci"]), torch.cat(rows["cj"]),
    )  # fmt: skip


__all__ = [
    "HELD_OUT_CLIPS",
    "BodyCopies",
    "Dataset",
    "SourceSequence",
    "WindowBatch",
    "build_dataset",
    "draw_windows",
    "load_body_kit",
    "mirror_motion",
    "training_clips",
    "vertex_mirror_map",
]
