"""Per-body work cached by the character's content: body parts and per-part SDF grids.

The same body read twice (another upload of the same file, the next job on a built-in body) gets the same key,
so only its first job pays for the grids (seconds on a 13k-vertex body). Two levels: a small in-process LRU,
and files under :func:`cache_dir` that every process on the machine (CLI runs, workers) shares.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from retarget_core.body_parts import BodyParts, body_parts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.energy.sdf import REFERENCE_HEIGHT_M, PartSDF, SDFParams, build_part_sdf, vertex_clusters

log = logging.getLogger(__name__)

CACHE_VERSION = 2
"""Bump when what is cached changes meaning (grid layout, parameters): old files are then ignored."""
MEMORY_ENTRIES = 16
CACHE_DIR_ENV = "RETARGET_CACHE_DIR"


@dataclass
class BodyAssets:
    """What the measures and the refinement stages precompute once per body."""

    key: str
    parts: BodyParts
    sdf: PartSDF


_MEMORY: OrderedDict[str, BodyAssets] = OrderedDict()


def cache_dir() -> Path | None:
    """``$RETARGET_CACHE_DIR`` (empty: no disk cache), default ``~/.cache/retarget/bodies``."""
    value = os.environ.get(CACHE_DIR_ENV)
    if value is not None:
        return Path(value) if value else None
    return Path.home() / ".cache" / "retarget" / "bodies"


def character_key(character: Character, mapping: JointMapping) -> str:
    """A content hash of the mesh, skin, skeleton rest pose, mapping and SDF parameters."""
    h = hashlib.sha1(f"v{CACHE_VERSION}:{SDFParams()!r}".encode())
    sk = character.skeleton
    for t in (character.vertices, character.faces, character.skin_joints, character.skin_weights,
              sk.rest_rotations, sk.rest_translations):  # fmt: skip
        h.update(t.detach().contiguous().numpy().tobytes())
    h.update(json.dumps([sk.parents, sorted(mapping.joints.items())]).encode())
    if character.has_accessories:  # the roles decide which triangles make the part volumes
        h.update(character.body_vertices.numpy().tobytes())
    return h.hexdigest()


def _remember(assets: BodyAssets) -> BodyAssets:
    _MEMORY[assets.key] = assets
    _MEMORY.move_to_end(assets.key)
    while len(_MEMORY) > MEMORY_ENTRIES:
        _MEMORY.popitem(last=False)
    return assets


def _read(path: Path) -> tuple[BodyParts, PartSDF] | None:
    try:
        parts, sdf = torch.load(path, weights_only=False)
        return parts, sdf
    except Exception as exc:  # a truncated or foreign file: rebuild
        log.warning("ignoring unreadable body cache %s: %s", path, exc)
        return None


def _write(path: Path, parts: BodyParts, sdf: PartSDF) -> None:
    """Atomically (temporary file + rename), so concurrent workers never read half a file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".part")
        with os.fdopen(fd, "wb") as fh:
            torch.save((parts, sdf), fh)
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("could not write body cache %s: %s", path, exc)


def body_assets(character: Character, mapping: JointMapping) -> tuple[BodyAssets, bool]:
    """The body's parts and SDF grids, and whether they came from a cache (memory or disk)."""
    key = character_key(character, mapping)
    if key in _MEMORY:
        _MEMORY.move_to_end(key)
        return _MEMORY[key], True
    folder = cache_dir()
    path = folder / f"{key}.pt" if folder is not None else None
    if path is not None and path.is_file() and (found := _read(path)) is not None:
        return _remember(BodyAssets(key, *found)), True
    parts = body_parts(character, mapping)
    sdf = body_sdf(character, parts)
    if path is not None:
        _write(path, parts, sdf)
    return _remember(BodyAssets(key, parts, sdf)), False


def body_sdf(character: Character, parts: BodyParts) -> PartSDF:
    """The part SDF grids of the body meshes only: accessory triangles make no part volume, and accessory vertices
    are put in clusters of their own that are never sampled (radius -inf: no culling test passes), so neither
    the metrics nor the collision stage test them or spend time on them."""
    if parts.body is None:
        return build_part_sdf(character, parts)
    sdf = build_part_sdf(replace(character, faces=parts.faces), parts)
    if sdf.clusters is not None:
        rest = character.vertices.float()
        apart = parts.vertex_part + parts.num_parts * (~parts.body).long()  # accessories never share a cluster
        size = SDFParams().cluster_m * character.height / REFERENCE_HEIGHT_M
        cl = vertex_clusters(rest, apart, size)
        accessory = cl.part >= parts.num_parts
        cl.part = cl.part % parts.num_parts
        cl.radius = torch.where(accessory, torch.full_like(cl.radius, -math.inf), cl.radius)
        sdf.clusters = cl
    return sdf


def part_sdf_for(character: Character, mapping: JointMapping) -> tuple[BodyParts, PartSDF]:
    """The body's parts and SDF grids (cached, see :func:`body_assets`)."""
    assets = body_assets(character, mapping)[0]
    return assets.parts, assets.sdf


def clear_memory() -> None:
    """Forget the in-process entries (tests; the disk cache stays)."""
    _MEMORY.clear()


__all__ = ["BodyAssets", "body_assets", "body_sdf", "cache_dir", "character_key", "clear_memory", "part_sdf_for"]
