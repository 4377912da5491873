"""Training poses of the learned collision resolver: the copy of the shared clips (not the held-out ones) and
their mirrors onto generated bodies, so the collisions are the ones the copy really makes on those bodies.

Built on :func:`retarget_core.model.data.build_dataset` (clips on a neutral source body, source hand contacts,
copy baseline per body); per body we keep every ``stride``-th frame, the source's hand contacts as a cluster-pair
table (those pairs are not collisions, see :mod:`collision_geometry`) and the frame's input collision matrix (to
draw colliding frames more often). Cached in one file per settings.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import roma
import torch
from torch import Tensor

from retarget_core.bodies.params import BodyParams
from retarget_core.body_cache import body_assets
from retarget_core.body_parts import BodyParts, body_parts
from retarget_core.character import Character
from retarget_core.energy.sdf import PartSDF
from retarget_core.mapping import map_joints
from retarget_core.model.collision_geometry import LIMB_ROWS, LimbPoints, collision_matrix, contact_exempt, limb_points
from retarget_core.model.collision_net import BodyRig, body_rig
from retarget_core.model.data import build_dataset, training_clips

log = logging.getLogger(__name__)


@dataclass
class BodyFrames:
    """One training body's frames ``(N, ...)``: local rotations ``(N, J, 4)``, translations ``(N, J, 3)``,
    contact pairs ``exempt (N, 6, 6)`` bool, the input collision matrix ``m_col (N, 6, 6)`` (m)."""

    params: BodyParams
    rot: Tensor
    trans: Tensor
    exempt: Tensor
    m_col: Tensor

    @property
    def colliding(self) -> Tensor:
        """``(N,)`` bool: a limb row of the input collision matrix is non-zero."""
        return self.m_col[:, list(LIMB_ROWS)].flatten(1).amax(-1) > 0


@dataclass
class CollisionData:
    bodies: list[BodyFrames]
    info: dict[str, object]


@dataclass
class BodyKitC:
    """What training needs of one body: the character, its parts, SDFs, limb points and rig."""

    character: Character
    parts: BodyParts
    sdf: PartSDF
    points: LimbPoints
    rig: BodyRig


def body_kit_c(params: BodyParams) -> BodyKitC:
    """The :class:`BodyKitC` of a generated body (parts and SDFs from the body cache)."""
    from retarget_core.bodies.makehuman import make_body

    ch = make_body(params)
    mapping = map_joints(ch.skeleton)
    assets, _ = body_assets(ch, mapping)
    return BodyKitC(ch, assets.parts, assets.sdf, limb_points(ch, assets.parts, assets.sdf), body_rig(ch, mapping, assets.parts))


def build_collision_data(clips: list[Path], bodies: list[BodyParams], stride: int, seed: int,
                         max_clip_frames: int = 600) -> CollisionData:  # fmt: skip
    """Copy poses of ``clips`` (and mirrors) on ``bodies``, every ``stride``-th frame, with contacts and M_col."""
    from retarget_core.bodies.makehuman import make_body

    t0 = time.perf_counter()
    data = build_dataset(clips, bodies, 0, 60, seed, max_clip_frames=max_clip_frames)
    src = make_body(data.source_params)
    src_parts = body_parts(src, map_joints(src.skeleton))
    src_cluster = torch.tensor(src_parts.cluster, dtype=torch.long)
    exempts: list[Tensor] = []
    picks: list[Tensor] = []
    for seq in data.sequences:
        n = seq.motion.num_frames
        hc = src_cluster[src_parts.vertex_part[seq.contact_i]] if seq.contact_i.numel() else seq.contact_i
        tc = src_cluster[src_parts.vertex_part[seq.contact_j]] if seq.contact_j.numel() else seq.contact_j
        exempts.append(contact_exempt(n, seq.contact_frame, hc, tc))
        picks.append(torch.arange(0, n, stride))
    out: list[BodyFrames] = []
    for b, copies in enumerate(data.bodies):
        rot = torch.cat([r[p] for r, p in zip(copies.copy_rot, picks, strict=True)])
        trans = torch.cat([t[p] for t, p in zip(copies.copy_trans, picks, strict=True)])
        exempt = torch.cat([e[p] for e, p in zip(exempts, picks, strict=True)])
        kit = body_kit_c(copies.params)
        m_col = collision_matrix(kit.sdf, kit.points, roma.unitquat_to_rotmat(rot), trans, exempt)
        out.append(BodyFrames(copies.params, rot, trans, exempt, m_col))
        log.info("body %d: %d frames, %d colliding (%.0f s)", b, len(rot), int(out[-1].colliding.sum()), time.perf_counter() - t0)
    info = {**data.info, "stride": stride, "frames_per_body": [len(b.rot) for b in out],
            "colliding_frames_per_body": [int(b.colliding.sum()) for b in out],
            "contact_exempt_frames_per_body": [int(b.exempt.flatten(1).any(-1).sum()) for b in out],
            "build_seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    return CollisionData(out, info)


def data_key(clips: list[Path], bodies: list[BodyParams], stride: int, seed: int) -> str:
    blob = json.dumps([[p.stem for p in clips], [b.model_dump() for b in bodies], stride, seed, "v1"])
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def get_collision_data(clip_dir: Path, bodies: list[BodyParams], stride: int, seed: int, cache_dir: Path) -> CollisionData:
    """The training set (from ``cache_dir`` when built before with the same clips, bodies and settings)."""
    clips = training_clips(clip_dir)
    path = cache_dir / f"collision-data-{data_key(clips, bodies, stride, seed)}.pt"
    if path.is_file():
        data: CollisionData = torch.load(path, weights_only=False)
        return data
    data = build_collision_data(clips, bodies, stride, seed)
    cache_dir.mkdir(parents=True, exist_ok=True)
    torch.save(data, path)
    return data


__all__ = ["BodyFrames", "BodyKitC", "CollisionData", "body_kit_c", "build_collision_data", "data_key", "get_collision_data"]
