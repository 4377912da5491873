"""Read any supported file into a normalised, mapped motion or character (the library's front door)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.errors import InvalidFileError, RetargetError
from retarget_core.io.formats import FileFormat, detect_format
from retarget_core.motion import Motion
from retarget_core.normalize import NormalizationReport, normalize_character, normalize_motion
from retarget_core.skeleton import Skeleton

BUILTIN_PREFIX = "builtin:"


@dataclass
class LoadedCharacter:
    """A character ready to be a target or a source body."""

    character: Character
    mapping: JointMapping
    normalization: NormalizationReport
    format: str
    notes: list[str] = field(default_factory=list)


@dataclass
class LoadedMotion:
    """A motion ready for retargeting, with what was found on the way."""

    motion: Motion
    mapping: JointMapping
    normalization: NormalizationReport
    format: str
    source_character: LoadedCharacter | None = None
    """The motion file's own skinned mesh, mapped and normalised, when it has one."""
    clips: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _read_any(
    path: Path, fps: float | None, with_motions: bool = True
) -> tuple[FileFormat, Character | None, list[Motion], list[str], dict[str, str]]:
    fmt = detect_format(path)
    if fmt == "bvh":
        from retarget_core.io.bvh import BvhNote, read_bvh

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", BvhNote)
            motion = read_bvh(path)
        return fmt, None, [motion], [str(w.message) for w in caught if issubclass(w.category, BvhNote)], {}
    if fmt == "fbx":
        from retarget_core.io.fbx import read_fbx

        contents = read_fbx(path, fps=fps)
    else:
        from retarget_core.io.gltf_read import read_gltf

        contents = read_gltf(path, fps=fps, with_motions=with_motions)
    humanoid = dict(getattr(contents, "humanoid", {}))  # the VRM humanoid bone map (glTF only)
    return fmt, contents.character, list(contents.motions), list(contents.notes), humanoid


def _pick_clip(motions: list[Motion], clip: str | None, label: str) -> Motion:
    if not motions:
        raise InvalidFileError("the file has no animation to retarget", label)
    if clip is None:
        return motions[0]
    for m in motions:
        if m.name == clip:
            return m
    if clip.isdigit() and int(clip) < len(motions):
        return motions[int(clip)]
    names = ", ".join(repr(m.name) for m in motions)
    raise InvalidFileError(f"no animation named {clip!r}; the file has {names}", label)


def _map(
    label: str, skeleton: Skeleton, override: dict[str, str] | None, vrm: dict[str, str] | None = None
) -> JointMapping:
    from retarget_core.mapping import map_joints, require_complete

    mapping = map_joints(skeleton, override, vrm=vrm)
    require_complete(mapping, label)
    return mapping


def load_motion(
    path: str | Path,
    *,
    clip: str | None = None,
    fps: float | None = None,
    unit: str | None = None,
    joint_map_override: dict[str, str] | None = None,
) -> LoadedMotion:
    """Read a BVH, glTF/GLB or FBX motion, map its joints and normalise it (metres, Y up, ground at 0).

    ``fps`` is the rate glTF/FBX animations are sampled at (BVH keeps its own; resample afterwards)."""
    path = Path(path)
    fmt, character, motions, notes, vrm = _read_any(path, fps)
    motion = _pick_clip(motions, clip, str(path))
    mapping = _map(f"motion {path.name}", motion.skeleton, joint_map_override, vrm)
    normalized, report = normalize_motion(motion, mapping, unit)
    source_character = None
    if character is not None:
        try:
            char_map = _map(f"character in {path.name}", character.skeleton, joint_map_override, vrm)
            body, body_report = normalize_character(character, char_map)
            source_character = LoadedCharacter(body, char_map, body_report, fmt, body_report.notes)
        except RetargetError as exc:
            notes.append(f"the file's mesh cannot serve as the source body: {exc}")
    return LoadedMotion(
        normalized, mapping, report, fmt, source_character, [m.name for m in motions], notes + report.notes
    )


def load_character(
    path_or_builtin: str | Path,
    *,
    unit: str | None = None,
    joint_map_override: dict[str, str] | None = None,
) -> LoadedCharacter:
    """Read a skinned character from glTF/GLB/FBX, or make a built-in body (``"builtin:<preset>"``)."""
    label = str(path_or_builtin)
    if label.startswith(BUILTIN_PREFIX):
        from retarget_core.bodies.presets import load_preset

        try:
            character = load_preset(label[len(BUILTIN_PREFIX) :])
        except ValueError as exc:
            raise RetargetError(str(exc)) from None
        fmt, notes, vrm = "builtin", list[str](), dict[str, str]()
    else:
        path = Path(path_or_builtin)
        fmt, maybe, _, notes, vrm = _read_any(path, None, with_motions=False)  # a target's clips are not used
        if fmt == "bvh" or maybe is None:
            raise InvalidFileError("a target character must be a skinned mesh (glTF/GLB or FBX with a skin)", label)
        character = maybe
    mapping = _map(f"character {Path(label).name}", character.skeleton, joint_map_override, vrm)
    normalized, report = normalize_character(character, mapping, unit)
    return LoadedCharacter(normalized, mapping, report, fmt, notes + report.notes)
