"""The hard held-out split (issue 22): whole clips of the hard kinds on extreme and real bodies, as a fixed case list.

``retarget_core/data/heldout_hard.json`` lists the clips (files under the shared data folder, with why each was
chosen and its tags), the generated bodies beyond the held-out ones (MakeHuman parameters), the real production
characters (files under the shared data folder) and the fixed cases (clip, body): each clip on three bodies, not
the full cross product. The five bodies of :mod:`retarget_core.heldout` are part of it. No clip is a training clip:
the ``motions/cmu`` ones are held-out clips of :mod:`retarget_core.heldout`, the others live outside the training
folder. ``retarget eval --split hard`` runs it (see :func:`split_cases`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from retarget_core import heldout
from retarget_core.bodies.params import BodyParams

SPLIT_FILE = Path(__file__).resolve().parent / "data" / "heldout_hard.json"
REAL_GROUP = "real"
MAKEHUMAN_GROUP = "makehuman"


@dataclass(frozen=True)
class HardClip:
    """A clip of the split: its name, its file relative to the shared data folder, its tags and why it is in."""

    name: str
    file: str
    tags: tuple[str, ...]
    why: str


@dataclass(frozen=True)
class RealCharacter:
    """A production character (not a MakeHuman body): its name and file relative to the shared data folder."""

    name: str
    file: str
    why: str


@dataclass(frozen=True)
class HardSplit:
    clips: tuple[HardClip, ...]
    bodies: tuple[BodyParams, ...]
    """The generated bodies: the held-out ones of :mod:`retarget_core.heldout`, then the split's own."""
    real_characters: tuple[RealCharacter, ...]
    cases: tuple[tuple[str, str], ...]
    """(clip name, body name), in the order they are run."""
    max_frames: int
    notes: str

    def body_names(self) -> list[str]:
        """Every body's name: the generated ones, then the real characters."""
        return [b.name for b in self.bodies] + [r.name for r in self.real_characters]


@lru_cache(maxsize=1)
def load_hard_split(path: Path = SPLIT_FILE) -> HardSplit:
    """The split as committed in ``retarget_core/data/heldout_hard.json``."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    clips = tuple(HardClip(c["name"], c["file"], tuple(c["tags"]), c["why"]) for c in data["clips"])
    own = tuple(BodyParams(**b) for b in data["bodies"])
    bodies = (heldout.load_split().bodies if data.get("heldout_bodies") else ()) + own
    real = tuple(RealCharacter(r["name"], r["file"], r["why"]) for r in data["real_characters"])
    cases = tuple((c["clip"], c["body"]) for c in data["cases"])
    return HardSplit(clips, bodies, real, cases, int(data["max_frames"]), data.get("notes", ""))


def clip_file(shared_data: Path, clip: HardClip) -> Path:
    """The clip's file under ``shared_data``; a missing one raises."""
    path = Path(shared_data) / clip.file
    if not path.is_file():
        raise FileNotFoundError(f"clip {clip.name} of the hard split is not at {path}")
    return path


def body_file(shared_data: Path, name: str, split: HardSplit | None = None) -> Path:
    """A body of the split as a file: a generated body's cached GLB (built on first use) or a real character's
    file under ``shared_data`` (a missing one raises)."""
    split = split or load_hard_split()
    for params in split.bodies:
        if params.name == name:
            return heldout.body_path(params)
    for real in split.real_characters:
        if real.name == name:
            path = Path(shared_data) / real.file
            if not path.is_file():
                raise FileNotFoundError(f"real character {name} of the hard split is not at {path}")
            return path
    raise KeyError(f"no body named {name!r} in the hard split")


def body_groups(shared_data: Path, split: HardSplit | None = None) -> dict[str, str]:
    """Body file stem (the table's body name) -> group: ``makehuman`` (generated bodies) or ``real``."""
    split = split or load_hard_split()
    groups = {heldout.body_stem(b): MAKEHUMAN_GROUP for b in split.bodies}
    groups.update({Path(r.file).stem: REAL_GROUP for r in split.real_characters})  # no file needed, none built
    return groups


def split_cases(
    shared_data: Path, split: HardSplit | None = None, only: list[str] | None = None
) -> list[tuple[Path, Path]]:
    """The fixed cases as (clip file, body file), in the split's order; with ``only``, those whose clip or body
    name contains one of its strings (none matching raises ValueError). Every file of a kept case must be there."""
    split = split or load_hard_split()
    names = [(c, b) for c, b in split.cases if not only or any(o in c or o in b for o in only)]
    if not names:
        raise ValueError(f"no case of the hard split names any of {only}")
    wanted = {c for c, _ in names}
    clips = {c.name: clip_file(shared_data, c) for c in split.clips if c.name in wanted}
    bodies = {b: body_file(shared_data, b, split) for b in dict.fromkeys(b for _, b in names)}
    return [(clips[clip], bodies[body]) for clip, body in names]


__all__ = [
    "HardClip",
    "HardSplit",
    "RealCharacter",
    "body_file",
    "body_groups",
    "clip_file",
    "load_hard_split",
    "split_cases",
]
