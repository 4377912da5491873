"""The fixed held-out split: CMU clips and generated bodies that no training may use.

``retarget_core/data/heldout.json`` lists the clips (file stems of ``../shared/data/motions/cmu``, with why each
was chosen), the held-out bodies (MakeHuman parameters, built with :func:`retarget_core.bodies.makehuman.make_body`)
and which shared character files are held out. Rules for training:

- exclude every held-out clip (:func:`is_heldout_clip`);
- never use the held-out bodies' parameter values, and sample training bodies away from them:
  :func:`near_heldout_body` says whether parameters fall within ``EXCLUSION_RADIUS`` of a held-out body in the
  normalised parameter space of :func:`body_distance`; :func:`sample_training_body_params` draws from the
  ordinary sampler and rejects such draws.

Bodies are built once and cached as GLB files (``cache_dir``, default ``~/.cache/retarget/heldout``), named by
their parameters' hash, so an evaluation can pass them as files (``retarget eval ... -b DIR``).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from retarget_core.bodies.params import BodyParams

SPLIT_FILE = Path(__file__).resolve().parent / "data" / "heldout.json"
CACHE_ENV = "RETARGET_HELDOUT_CACHE"
DEFAULT_CACHE = Path.home() / ".cache" / "retarget" / "heldout"
# Normalisation of each parameter in body_distance: the 0..1 macros as they are, age over 40 years, height over
# 0.25 m.
AGE_SCALE_Y = 40.0
HEIGHT_SCALE_M = 0.25
EXCLUSION_RADIUS = 0.3  # 0.3 of a macro range, 12 years or 7.5 cm
MAX_REJECTIONS = 1000


@dataclass(frozen=True)
class HeldoutClip:
    """A held-out clip: its file stem, what it shows, and its tags (contact, walk, bend, ...)."""

    name: str
    why: str
    tags: tuple[str, ...]


@dataclass(frozen=True)
class HeldoutSplit:
    clips: tuple[HeldoutClip, ...]
    bodies: tuple[BodyParams, ...]
    shared_bodies: tuple[str, ...]
    notes: str


SOURCE_BODY = "builtin:male_average"
"""The body the held-out clips are performed by when sent as GLBs (the judge's "clip on an average body")."""


@lru_cache(maxsize=1)
def load_split(path: Path = SPLIT_FILE) -> HeldoutSplit:
    """The split as committed in ``retarget_core/data/heldout.json``."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    clips = tuple(HeldoutClip(c["name"], c["why"], tuple(c["tags"])) for c in data["clips"])
    bodies = tuple(BodyParams(**b) for b in data["bodies"])
    return HeldoutSplit(clips, bodies, tuple(data.get("shared_bodies", [])), data.get("notes", ""))


def heldout_clip_names() -> list[str]:
    """File stems of the held-out clips."""
    return [c.name for c in load_split().clips]


def is_heldout_clip(path_or_name: str | Path) -> bool:
    """Whether a clip (a path or a file stem) is held out."""
    return Path(path_or_name).stem in set(heldout_clip_names())


def clip_paths(motions_dir: str | Path) -> list[Path]:
    """Paths of the held-out clips in ``motions_dir`` (the shared ``motions/cmu`` folder); missing files raise."""
    out = []
    for name in heldout_clip_names():
        p = Path(motions_dir) / f"{name}.bvh"
        if not p.is_file():
            raise FileNotFoundError(f"held-out clip {name} is not in {motions_dir}")
        out.append(p)
    return out


def training_clip_paths(motions_dir: str | Path) -> list[Path]:
    """Every ``.bvh`` in ``motions_dir`` that is not held out (what training may use)."""
    return [p for p in sorted(Path(motions_dir).glob("*.bvh")) if not is_heldout_clip(p)]


def _vector(p: BodyParams) -> np.ndarray:
    from retarget_core.bodies.presets import typical_height

    height = p.height if p.height is not None else typical_height(p.gender, p.age)
    return np.array(
        [p.gender, p.weight, p.muscle, p.proportions, p.age / AGE_SCALE_Y, height / HEIGHT_SCALE_M], dtype=np.float64
    )


def body_distance(a: BodyParams, b: BodyParams) -> float:
    """Euclidean distance of two bodies' parameters, each normalised (see the module constants)."""
    return float(np.linalg.norm(_vector(a) - _vector(b)))


def near_heldout_body(params: BodyParams, radius: float = EXCLUSION_RADIUS) -> bool:
    """Whether ``params`` lie within ``radius`` of a held-out body (training must not use them)."""
    return any(body_distance(params, h) < radius for h in load_split().bodies)


def sample_training_body_params(rng: np.random.Generator, name: str = "sampled") -> BodyParams:
    """:func:`retarget_core.bodies.presets.sample_body_params`, redrawn while near a held-out body."""
    from retarget_core.bodies.presets import sample_body_params

    for _ in range(MAX_REJECTIONS):
        params = sample_body_params(rng, name)
        if not near_heldout_body(params):
            return params
    raise RuntimeError("could not sample a body away from the held-out bodies")


def cache_dir() -> Path:
    """Where built held-out bodies are kept (``$RETARGET_HELDOUT_CACHE`` or ``~/.cache/retarget/heldout``)."""
    return Path(os.environ.get(CACHE_ENV) or DEFAULT_CACHE)


def body_stem(params: BodyParams) -> str:
    """The file stem of a body's cached GLB: its name and a 12-hex-digit hash of its parameters."""
    return f"{params.name}-{hashlib.sha1(params.model_dump_json().encode()).hexdigest()[:12]}"


def body_path(params: BodyParams, directory: Path | None = None) -> Path:
    """The cached GLB of one held-out body, built on first use."""
    directory = Path(directory or cache_dir())
    path = directory / f"{body_stem(params)}.glb"
    if not path.is_file():
        from retarget_core.bodies.makehuman import make_body
        from retarget_core.io.gltf_write import write_glb

        directory.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        write_glb(make_body(params), None, tmp)
        tmp.replace(path)
    return path


def body_paths(directory: Path | None = None) -> list[Path]:
    """GLB paths of every held-out body (built and cached on first use)."""
    return [body_path(p, directory) for p in load_split().bodies]


__all__ = [
    "EXCLUSION_RADIUS",
    "HeldoutClip",
    "HeldoutSplit",
    "body_distance",
    "body_path",
    "body_paths",
    "body_stem",
    "cache_dir",
    "clip_paths",
    "heldout_clip_names",
    "is_heldout_clip",
    "load_split",
    "near_heldout_body",
    "sample_training_body_params",
    "training_clip_paths",
]
