"""BVH (Biovision Hierarchy) reading and writing.

:func:`read_bvh` returns the clip RAW: file units and file axes, untouched (normalising to metres / Y up is
another module's job). The reader is hand-written and bounded:

* the hierarchy is read line by line with a small state machine (no recursion, no regular expressions);
  lines longer than :data:`MAX_HIERARCHY_LINE` characters are refused;
* the MOTION block is parsed in one vectorised pass (``numpy.loadtxt``) after cheap checks on the declared
  frame count, the number of lines and the longest line, so a hostile file cannot make it allocate more than a
  small multiple of its own size;
* every limit comes from :func:`retarget_core.config.get_settings` (``max_file_bytes``, ``max_frames``,
  ``max_joints``, ``max_accessor_elements`` for frames x joints).

Conventions of the returned :class:`~retarget_core.motion.Motion`:

* one joint per ROOT/JOINT, in file order; every ``End Site`` becomes an extra leaf joint named
  ``<parent>_End`` with its OFFSET and identity rotation (it is not animated), so bone directions to end sites
  are known;
* ``rest_rotations`` are identity and ``rest_translations`` are the OFFSETs;
* rotations come from each joint's rotation channels in the order the file lists them: ``Zrotation Yrotation
  Xrotation`` means ``R = Rz * Ry * Rx`` (intrinsic ``"ZYX"``), in degrees; any order and any subset is read;
* translations: a joint with position channels (the root, or any joint with 6 channels) gets
  ``OFFSET + position channel values`` -- the OFFSET is *not* dropped (the CMU CC_Base files need this: their
  root's position channels combine with its OFFSET); a joint without position channels repeats its OFFSET;
* ``fps = 1 / Frame Time``, snapped to the nearest whole number when the frame time is that number's
  reciprocal printed to the file's precision (``0.016667`` -> 60, ``.0083333`` -> 120, ``0.033367`` stays
  29.97...).

Recoverable oddities (duplicate joint names, rows beyond the declared frame count) are reported with
:class:`BvhNote` warnings (``warnings.catch_warnings(record=True)`` collects them).
"""

from __future__ import annotations

import io
import math
import warnings
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np
import roma
import torch

from retarget_core import rotations as rot
from retarget_core.config import get_settings
from retarget_core.errors import InvalidFileError, LimitExceededError, UnsupportedFileError
from retarget_core.io.accessors import ParseBudget
from retarget_core.kinematics import forward_kinematics
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton

MAX_HIERARCHY_LINE = 64 * 1024
"""Longest hierarchy line accepted (characters); real files stay under a few hundred."""

MAX_JOINT_NAME_CHARS = 1000
"""Longest joint name accepted (characters); names travel into mapping reports, messages and the database."""

MAX_CHARS_PER_VALUE = 48
"""Generous upper bound on the characters one MOTION value takes, separator included."""

MIN_FRAME_TIME = 1e-4
"""Shortest accepted Frame Time (s): 10,000 frames per second."""
MAX_FRAME_TIME = 10.0
"""Longest accepted Frame Time (s): one frame every 10 seconds."""
MAX_COORDINATE = 1e6
"""Largest OFFSET or position channel value (file units; a kilometre in centimetres is 1e5)."""
BYTES_PER_FRAME_JOINT = 160
"""What reading one joint of one frame costs (float64 translations and quaternions, Euler conversions)."""

END_SUFFIX = "_End"

_AXES = "XYZ"


class BvhNote(UserWarning):
    """Something in a BVH file was odd but could be read (reported with :func:`warnings.warn`)."""


@dataclass
class _Joint:
    name: str
    parent: int
    line: int
    offset: tuple[float, float, float] | None = None
    channels: list[str] = field(default_factory=list)  # normalised: "Xposition", "Zrotation", ...
    end_site: bool = False


# --------------------------------------------------------------------------------------------------- reading


class _Lines:
    """Hierarchy lines as token lists, with 1-based line numbers; refuses over-long lines."""

    def __init__(self, raw: bytes, label: str) -> None:
        self.raw = raw
        self.label = label
        self.pos = 0
        self.line = 0
        self.tokens: list[str] = []
        self.index = 0

    def next_line(self) -> list[str] | None:
        """Tokens of the next line (possibly empty) or None at the end of the file."""
        if self.pos >= len(self.raw):
            return None
        nl = self.raw.find(b"\n", self.pos, self.pos + MAX_HIERARCHY_LINE + 1)
        if nl < 0:
            if len(self.raw) - self.pos > MAX_HIERARCHY_LINE:
                raise InvalidFileError(
                    f"line {self.line + 1} is longer than {MAX_HIERARCHY_LINE} characters", self.label
                )
            nl = len(self.raw)
        text = self.raw[self.pos : nl].decode("utf-8", errors="replace")
        self.pos = nl + 1
        self.line += 1
        return text.split()

    def fill(self) -> bool:
        """Make sure an unread token is buffered; False at the end of the file."""
        while self.index >= len(self.tokens):
            toks = self.next_line()
            if toks is None:
                return False
            self.tokens, self.index = toks, 0
        return True

    def peek(self) -> str | None:
        return self.tokens[self.index] if self.fill() else None

    def take(self, what: str) -> str:
        """The next token; InvalidFileError naming ``what`` at the end of the file."""
        if not self.fill():
            raise InvalidFileError(f"the file ends early: expected {what} after line {self.line}", self.label)
        tok = self.tokens[self.index]
        self.index += 1
        return tok

    def rest_of_line(self) -> list[str]:
        """The unread tokens of the current line (consumed)."""
        out = self.tokens[self.index :]
        self.index = len(self.tokens)
        return out

    def error(self, problem: str) -> InvalidFileError:
        return InvalidFileError(f"line {self.line}: {problem}", self.label)


def _number(tok: str, what: str, lines: _Lines) -> float:
    try:
        value = float(tok)
    except ValueError:
        raise lines.error(f"{what} {tok!r} is not a number") from None
    if not math.isfinite(value):
        raise lines.error(f"{what} is {tok}")
    return value


def _channel_name(tok: str, lines: _Lines) -> str:
    low = tok.lower()
    if len(low) >= 2 and low[0] in "xyz" and low[1:] in ("position", "rotation"):
        return low[0].upper() + low[1:]
    raise UnsupportedFileError(
        f"line {lines.line}: unsupported channel {tok!r} (expected X/Y/Z position/rotation)", lines.label
    )


def _expect_hierarchy(lines: _Lines) -> None:
    """Consume the HIERARCHY keyword that opens the file."""
    first = lines.peek()
    if first is None:
        raise InvalidFileError("the file is empty", lines.label)
    if first.upper() != "HIERARCHY":
        raise lines.error(f"expected HIERARCHY, found {first[:40]!r}")
    lines.take("HIERARCHY")


class _Hierarchy:
    """The hierarchy parser's state: the joints read so far (file order) and the stack of open joint blocks."""

    def __init__(self, lines: _Lines, max_joints: int) -> None:
        self.lines = lines
        self.max_joints = max_joints
        self.joints: list[_Joint] = []
        self.stack: list[int] = []

    @property
    def current(self) -> _Joint | None:
        """The innermost open joint."""
        return self.joints[self.stack[-1]] if self.stack else None

    def _check_name(self, name_tokens: list[str], end_site: bool) -> None:
        """Refuse a nameless ROOT/JOINT, an over-long name and one joint too many."""
        lines = self.lines
        if not end_site and not name_tokens:
            raise lines.error("a ROOT/JOINT has no name")
        chars = sum(map(len, name_tokens)) + len(name_tokens) - 1
        if chars > MAX_JOINT_NAME_CHARS:
            raise LimitExceededError(f"line {lines.line}: a joint name of {chars} characters (the limit is "
                                     f"{MAX_JOINT_NAME_CHARS}, MAX_JOINT_NAME_CHARS)", lines.label)  # fmt: skip
        if len(self.joints) >= self.max_joints:
            raise LimitExceededError(f"more than {self.max_joints} joints (setting max_joints)", lines.label)

    def open_joint(self, name_tokens: list[str], parent: int, end_site: bool) -> None:
        """A ROOT, JOINT or End Site block named by ``name_tokens`` (its '{' may end the name or follow it)."""
        brace = False
        if name_tokens and name_tokens[-1].endswith("{"):
            last = name_tokens[-1][:-1]
            name_tokens = name_tokens[:-1] + ([last] if last else [])
            brace = True
        self._check_name(name_tokens, end_site)
        if not brace:
            tok = self.lines.take("'{'")
            if tok != "{":
                raise self.lines.error(f"expected '{{', found {tok[:40]!r}")
        # End Sites get their final name (after duplicate parents are renamed) in _unique_names.
        name = self.joints[parent].name + END_SUFFIX if end_site else " ".join(name_tokens)
        self.joints.append(_Joint(name=name, parent=parent, line=self.lines.line, end_site=end_site))
        self.stack.append(len(self.joints) - 1)

    def ends_early(self) -> InvalidFileError:
        """The error for a file that ends before MOTION."""
        if self.stack:
            return InvalidFileError(
                f"the file ends inside joint {self.joints[self.stack[-1]].name!r} (missing '}}')", self.lines.label
            )
        return InvalidFileError("the file has no MOTION section", self.lines.label)

    def motion(self) -> list[_Joint]:
        """The joints, at the MOTION keyword (every block closed, at least one ROOT)."""
        current = self.current
        if current is not None:
            raise self.lines.error(f"MOTION inside joint {current.name!r} (missing '}}')")
        if not self.joints:
            raise self.lines.error("MOTION before any ROOT")
        return self.joints

    def root(self) -> None:
        if self.stack:
            raise self.lines.error("ROOT inside another joint")
        self.open_joint(self.lines.rest_of_line(), -1, False)

    def joint(self) -> None:
        current = self.current
        if current is None or current.end_site:
            raise self.lines.error("JOINT outside a ROOT or inside an End Site")
        self.open_joint(self.lines.rest_of_line(), self.stack[-1], False)

    def end_site(self) -> None:
        lines, current = self.lines, self.current
        site = lines.take("'Site'")
        if site.upper() != "SITE":
            raise lines.error(f"expected 'End Site', found 'End {site[:40]}'")
        if current is None or current.end_site:
            raise lines.error("End Site outside a joint")
        self.open_joint(lines.rest_of_line(), self.stack[-1], True)

    def offset(self) -> None:
        lines, current = self.lines, self.current
        if current is None:
            raise lines.error("OFFSET outside a joint")
        if current.offset is not None:
            raise lines.error(f"second OFFSET in joint {current.name!r}")
        x, y, z = (_number(lines.take("an OFFSET value"), "OFFSET value", lines) for _ in range(3))
        current.offset = (x, y, z)

    def channels(self) -> None:
        lines, current = self.lines, self.current
        if current is None:
            raise lines.error("CHANNELS outside a joint")
        if current.channels:
            raise lines.error(f"second CHANNELS in joint {current.name!r}")
        count_tok = lines.take("a channel count")
        if not count_tok.isdigit() or int(count_tok) > 6:
            raise lines.error(f"channel count {count_tok[:40]!r} is not a whole number from 0 to 6")
        names = [_channel_name(lines.take("a channel name"), lines) for _ in range(int(count_tok))]
        if len(set(names)) != len(names):
            raise lines.error(f"joint {current.name!r} repeats a channel: {' '.join(names)}")
        if current.end_site and names:
            raise lines.error("an End Site cannot have channels")
        current.channels = names

    def close(self) -> None:
        current = self.current
        if current is None:
            raise self.lines.error("'}' without an open joint")
        if current.offset is None:
            raise self.lines.error(f"joint {current.name!r} has no OFFSET")
        self.stack.pop()


def _parse_hierarchy(lines: _Lines, max_joints: int) -> list[_Joint]:
    """Joints in file order; stops after the MOTION keyword."""
    _expect_hierarchy(lines)
    h = _Hierarchy(lines, max_joints)
    keywords = {"ROOT": h.root, "JOINT": h.joint, "END": h.end_site, "OFFSET": h.offset, "CHANNELS": h.channels,
                "}": h.close}  # fmt: skip
    while True:
        if lines.peek() is None:
            raise h.ends_early()
        key = lines.take("a keyword").upper()
        if key == "MOTION":
            return h.motion()
        handler = keywords.get(key)
        if handler is None:
            raise lines.error(f"unexpected {key[:40]!r}")
        handler()


def _header_value(lines: _Lines, key: str) -> str:
    """The value of the ``key: value`` line that comes next (blank lines skipped)."""
    while True:
        toks = lines.next_line()
        if toks is None:
            raise InvalidFileError(f"the file ends before the '{key}:' line of the MOTION section", lines.label)
        if toks:
            break
    text = " ".join(toks)
    label, sep, value = text.partition(":")
    if not sep or " ".join(label.split()).lower() != key.lower() or not value.strip():
        raise lines.error(f"expected '{key}: <value>', found {text[:60]!r}")
    return value.strip()


def _snapped_fps(frame_time_text: str, frame_time: float) -> float:
    """1 / frame time, snapped to a whole number when the frame time is its printed reciprocal."""
    fps = 1.0 / frame_time
    nearest = round(fps)
    try:
        exponent = Decimal(frame_time_text).as_tuple().exponent
    except InvalidOperation:
        return fps
    if nearest >= 1 and isinstance(exponent, int):
        tolerance = 0.5 * 10.0**exponent + 1e-12
        if abs(frame_time - 1.0 / nearest) <= tolerance:
            return float(nearest)
    return fps


def _motion_values(data: bytes, frames: int, channels: int, first_line: int, label: str) -> np.ndarray:
    """The MOTION rows as ``(frames, channels)`` float64, after bounded sanity checks."""
    line_count = data.count(b"\n") + 1
    if line_count > 2 * frames + 16:
        raise InvalidFileError(
            f"the MOTION section has {line_count} lines for {frames} declared frames (one line per frame expected)",
            label,
        )
    newline = np.flatnonzero(np.frombuffer(data, dtype=np.uint8) == 10)
    bounds = np.concatenate(([-1], newline, [len(data)]))
    lengths = np.diff(bounds) - 1
    longest = int(lengths.max()) if len(lengths) else 0
    limit = channels * MAX_CHARS_PER_VALUE + 256
    if longest > limit:
        row = int(np.argmax(lengths))
        raise InvalidFileError(
            f"line {first_line + row} has {longest} characters, too many for a frame of {channels} values", label
        )
    text = data.decode("latin-1")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": reported below
            values = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2, max_rows=frames + 1, comments=None)
    except ValueError:
        raise _diagnose_rows(text, channels, first_line, label) from None
    if values.shape[0] and values.shape[1] != channels:
        raise InvalidFileError(
            f"frame 1 (line {first_line}) has {values.shape[1]} values; the hierarchy declares {channels} channels",
            label,
        )
    found = values.shape[0]
    if found < frames:
        raise InvalidFileError(f"the header declares {frames} frames but the MOTION section holds {found}", label)
    if found > frames:
        warnings.warn(BvhNote(f"{label}: rows after the {frames} declared frames are ignored"), stacklevel=3)
        values = values[:frames]
    return values


def _diagnose_rows(text: str, channels: int, first_line: int, label: str) -> InvalidFileError:
    """A precise error for MOTION rows numpy refused (bounded: the line count was checked before)."""
    frame = 0
    for offset, line in enumerate(text.split("\n")):
        toks = line.split()
        if not toks:
            continue
        frame += 1
        where = f"frame {frame} (line {first_line + offset})"
        for tok in toks:
            try:
                float(tok)
            except ValueError:
                return InvalidFileError(f"{where}: value {tok[:40]!r} is not a number", label)
        if len(toks) != channels:
            return InvalidFileError(
                f"{where} has {len(toks)} values, expected {channels} (incomplete or malformed row)", label
            )
    return InvalidFileError("the MOTION section could not be read as numbers", label)


def _unique_names(joints: list[_Joint], label: str) -> None:
    """Rename repeated joint names ``name_2``, ``name_3``... (with a note), then name End Sites after their
    (renamed) parents; an End Site name that collides with a joint is suffixed too."""
    seen: set[str] = set()

    def unique(name: str) -> str:
        k = 2
        while f"{name}_{k}" in seen:
            k += 1
        return f"{name}_{k}"

    for joint in joints:
        if joint.end_site:
            continue
        if joint.name in seen:
            new = unique(joint.name)
            warnings.warn(
                BvhNote(f"{label}: duplicate joint name {joint.name!r} (line {joint.line}) renamed {new!r}"),
                stacklevel=3,
            )
            joint.name = new
        seen.add(joint.name)
    for joint in joints:
        if joint.end_site:
            joint.name = joints[joint.parent].name + END_SUFFIX
            if joint.name in seen:
                new = unique(joint.name)
                warnings.warn(BvhNote(f"{label}: End Site name {joint.name!r} is taken; named {new!r}"), stacklevel=3)
                joint.name = new
            seen.add(joint.name)


def read_bvh(path: str | Path, *, name: str | None = None) -> Motion:
    """The clip in the BVH file at ``path``, raw (file units and axes); see the module docstring.

    Raises InvalidFileError (malformed, truncated, non-finite values, frame count mismatch),
    UnsupportedFileError (unknown channel types) or LimitExceededError (size, frames, joints).
    """
    path = Path(path)
    label = str(path)
    settings = get_settings()
    size = path.stat().st_size
    if size > settings.max_file_bytes:
        raise LimitExceededError(
            f"the file has {size} bytes, over the limit of {settings.max_file_bytes} (setting max_file_bytes)", label
        )
    raw = path.read_bytes()[: settings.max_file_bytes + 1]
    if len(raw) > settings.max_file_bytes:
        raise LimitExceededError(
            f"the file is over the limit of {settings.max_file_bytes} bytes (setting max_file_bytes)", label
        )
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    if b"\r" in raw:
        raw = raw.replace(b"\r\n", b"\n").replace(b"\r", b"\n")

    lines = _Lines(raw, label)
    joints = _parse_hierarchy(lines, settings.max_joints)
    if lines.rest_of_line():
        raise lines.error("unexpected text after MOTION")

    frames_text = _header_value(lines, "Frames")
    if not frames_text.isdigit():
        raise lines.error(f"frame count {frames_text[:40]!r} is not a whole number")
    if len(frames_text) > 18 or int(frames_text) > settings.max_frames:
        raise LimitExceededError(
            f"the header declares {frames_text[:40]} frames, over the limit of {settings.max_frames} (setting max_frames)",
            label,
        )
    frames = int(frames_text)
    if frames == 0:
        raise lines.error("the header declares 0 frames")
    frame_time_text = _header_value(lines, "Frame Time")
    try:
        frame_time = float(frame_time_text)
    except ValueError:
        raise lines.error(f"frame time {frame_time_text[:40]!r} is not a number") from None
    if not math.isfinite(frame_time) or frame_time <= 0.0:
        raise lines.error(f"frame time must be a positive number, found {frame_time_text[:40]!r}")
    if not MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME:
        raise lines.error(f"Frame Time {frame_time_text[:40]} s is outside {MIN_FRAME_TIME:g} to {MAX_FRAME_TIME:g} s "
                          f"({1 / MAX_FRAME_TIME:g} to {1 / MIN_FRAME_TIME:g} frames per second)")
    fps = _snapped_fps(frame_time_text, frame_time)
    _check_offsets(joints, label)

    num_joints = len(joints)
    if frames * num_joints > settings.max_accessor_elements:
        raise LimitExceededError(
            f"{frames} frames x {num_joints} joints is over the limit of {settings.max_accessor_elements} (setting max_accessor_elements)",
            label,
        )
    ParseBudget(label).charge(frames * num_joints * BYTES_PER_FRAME_JOINT, f"{frames} frames x {num_joints} joints")
    num_channels = sum(len(j.channels) for j in joints)
    if num_channels == 0:
        raise InvalidFileError("no joint has channels: the file holds no motion", label)

    values = _motion_values(raw[lines.pos :], frames, num_channels, lines.line + 1, label)
    bad = ~np.isfinite(values)
    if bad.any():
        frame, column = (int(v) for v in np.argwhere(bad)[0])
        joint, channel = _column_owner(joints, column)
        raise InvalidFileError(
            f"frame {frame + 1}: channel {channel} of joint {joint!r} is {values[frame, column]}", label
        )
    _check_positions(joints, values, label)

    _unique_names(joints, label)
    return _build_motion(joints, values, fps, name if name is not None else path.stem)


def _check_offsets(joints: list[_Joint], label: str) -> None:
    """Refuse a skeleton without size (every OFFSET 0) or with offsets no real skeleton has."""
    offsets = np.array([j.offset for j in joints], dtype=np.float64)
    if len(joints) > 1 and not np.abs(offsets[1:]).any():
        raise InvalidFileError("every OFFSET below the root is 0: the skeleton has no size", label)
    big = float(np.abs(offsets).max()) if offsets.size else 0.0
    if big > MAX_COORDINATE:
        raise InvalidFileError(f"an OFFSET of {big:.3g} is over the limit of {MAX_COORDINATE:g} (not a skeleton)", label)


def _check_positions(joints: list[_Joint], values: np.ndarray, label: str) -> None:
    """Refuse position channels no real motion has (|value| over MAX_COORDINATE)."""
    columns = [c for c, (_, channel) in enumerate(_channel_owners(joints)) if channel.endswith("position")]
    if not columns:
        return
    pos = np.abs(values[:, columns])
    if float(pos.max()) > MAX_COORDINATE:
        frame, k = (int(v) for v in np.unravel_index(int(np.argmax(pos)), pos.shape))
        joint, channel = _column_owner(joints, columns[k])
        raise InvalidFileError(f"frame {frame + 1}: {channel} of joint {joint!r} is {values[frame, columns[k]]:.3g}, "
                               f"over the limit of {MAX_COORDINATE:g} (not a motion)", label)


def _channel_owners(joints: list[_Joint]) -> list[tuple[str, str]]:
    return [(j.name, c) for j in joints for c in j.channels]


def _column_owner(joints: list[_Joint], column: int) -> tuple[str, str]:
    for joint in joints:
        if column < len(joint.channels):
            return joint.name, joint.channels[column]
        column -= len(joint.channels)
    raise IndexError(column)


def _build_motion(joints: list[_Joint], values: np.ndarray, fps: float, name: str) -> Motion:
    frames = values.shape[0]
    num_joints = len(joints)
    offsets = np.array([j.offset for j in joints], dtype=np.float64)  # (J, 3)
    translations = np.repeat(offsets[None], frames, axis=0)  # (F, J, 3)
    rotations = rot.identity(frames, num_joints, dtype=torch.float64)  # (F, J, 4)

    groups: dict[str, tuple[list[int], list[list[int]]]] = {}
    pos_joint: list[int] = []
    pos_axis: list[int] = []
    pos_column: list[int] = []
    column = 0
    for j, joint in enumerate(joints):
        rot_columns: list[int] = []
        convention = ""
        for channel in joint.channels:
            axis = channel[0]
            if channel.endswith("rotation"):
                convention += axis
                rot_columns.append(column)
            else:
                pos_joint.append(j)
                pos_axis.append(_AXES.index(axis))
                pos_column.append(column)
            column += 1
        if convention:
            members, cols = groups.setdefault(convention, ([], []))
            members.append(j)
            cols.append(rot_columns)

    if pos_joint:
        translations[:, pos_joint, pos_axis] += values[:, pos_column]
    for convention, (members, cols) in groups.items():
        angles = torch.from_numpy(values[:, np.array(cols)])  # (F, n, D)
        rotations[:, members] = rot.from_euler(convention, angles, degrees=True)

    skeleton = Skeleton(
        names=[j.name for j in joints],
        parents=[j.parent for j in joints],
        rest_translations=torch.from_numpy(offsets).float(),
        rest_rotations=rot.identity(num_joints),
    )
    return Motion(
        skeleton=skeleton,
        fps=fps,
        rotations=rot.normalize(rotations).float(),
        translations=torch.from_numpy(translations).float(),
        name=name,
    )


# --------------------------------------------------------------------------------------------------- writing


def _to_euler(convention: str, q: torch.Tensor) -> torch.Tensor:
    """Euler angles ``(..., 3)`` in degrees. roma >= 1.8 returns one tensor, older roma a list: accept both
    (``rotations.to_euler`` assumes the list and fails on roma 1.8)."""
    angles = roma.unitquat_to_euler(convention, q, degrees=True)
    return angles if isinstance(angles, torch.Tensor) else torch.stack(list(angles), dim=-1)


def _depth_first(parents: list[int]) -> list[int]:
    children: list[list[int]] = [[] for _ in parents]
    roots: list[int] = []
    for j, p in enumerate(parents):
        (roots if p < 0 else children[p]).append(j)
    order: list[int] = []
    stack = list(reversed(roots))
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children[j]))
    return order


def _safe_names(names: list[str]) -> list[str]:
    """Names without whitespace (other BVH readers split on it), still unique."""
    out: list[str] = []
    seen: set[str] = set()
    for i, name in enumerate(names):
        base = "_".join(name.split()) or f"joint{i}"
        new, k = base, 2
        while new in seen:
            new, k = f"{base}_{k}", k + 1
        seen.add(new)
        out.append(new)
    return out


@dataclass
class _Baked:
    """A motion with its rest rotations baked in: offsets ``(J, 3)`` (rest positions relative to the parent, world
    axes), local rotations ``(F, J, 4)`` and what position channels must hold ``(F, J, 3)``; moves ``(J,)``
    whether a joint's translation leaves its rest offset in some frame."""

    offsets: torch.Tensor
    local_rot: torch.Tensor
    position_values: torch.Tensor
    moves: list[bool]


def _bake(motion: Motion) -> _Baked:
    """Local rotations ``Rw0_p * r * inv(Rw0_j)`` and offsets that reproduce the motion's joint positions."""
    skeleton = motion.skeleton
    parents = list(skeleton.parents)
    num_joints = skeleton.num_joints
    rest_rot, rest_pos = forward_kinematics(
        parents, rot.normalize(skeleton.rest_rotations.double()), skeleton.rest_translations.double()
    )
    grot, gpos = forward_kinematics(parents, rot.normalize(motion.rotations.double()), motion.translations.double())
    written_world = rot.mul(grot, rot.inv(rest_rot))  # (F, J, 4)
    offsets = rest_pos.clone()
    local_rot = written_world.clone()
    local_pos = gpos.clone()
    for j, p in enumerate(parents):
        if p >= 0:
            offsets[j] = rest_pos[j] - rest_pos[p]
            inv_p = rot.inv(written_world[:, p])
            local_rot[:, j] = rot.mul(inv_p, written_world[:, j])
            local_pos[:, j] = rot.apply(inv_p, gpos[:, j] - gpos[:, p])
    position_values = local_pos - offsets  # (F, J, 3): what position channels must hold
    extent = float((rest_pos.max(0).values - rest_pos.min(0).values).norm()) if num_joints else 1.0
    tolerance = 1e-6 * max(1.0, extent)
    moves = (position_values.abs().amax(dim=(0, 2)) > tolerance).tolist() if motion.num_frames else [False] * num_joints
    return _Baked(offsets, local_rot, position_values, moves)


def _end_sites(parents: list[int], names: list[str], moves: list[bool]) -> list[bool]:
    """``(J,)`` leaf joints named ``*_End`` whose translation stays at rest: written as End Sites."""
    has_children = [False] * len(parents)
    for p in parents:
        if p >= 0:
            has_children[p] = True
    return [
        parents[j] >= 0 and not has_children[j] and names[j].endswith(END_SUFFIX) and not moves[j]
        for j in range(len(parents))
    ]


def _hierarchy(motion: Motion, baked: _Baked, order: str) -> tuple[list[str], list[torch.Tensor]]:
    """The HIERARCHY section's lines and the motion table's columns ``(F, 3)`` in channel order."""
    parents = list(motion.skeleton.parents)
    num_joints = len(parents)
    end_site = _end_sites(parents, list(motion.skeleton.names), baked.moves)
    with_position = [parents[j] < 0 or baked.moves[j] for j in range(num_joints)]
    euler = _to_euler(order, rot.normalize(baked.local_rot))  # (F, J, 3) in ``order``, degrees
    names = _safe_names(list(motion.skeleton.names))
    lines = ["HIERARCHY"]
    columns: list[torch.Tensor] = []
    depth_of = [0] * num_joints
    open_blocks: list[int] = []  # joints whose '}' is pending
    rot_channels = " ".join(f"{axis}rotation" for axis in order)
    for j in _depth_first(parents):
        p = parents[j]
        depth_of[j] = depth_of[p] + 1 if p >= 0 else 0
        while open_blocks and open_blocks[-1] != p:
            closed = open_blocks.pop()
            lines.append("\t" * depth_of[closed] + "}")
        pad = "\t" * depth_of[j]
        ox, oy, oz = baked.offsets[j].tolist()
        if end_site[j]:
            lines += [pad + "End Site", pad + "{", pad + f"\tOFFSET {ox:.6f} {oy:.6f} {oz:.6f}", pad + "}"]
            continue
        lines += [
            pad + ("ROOT " if p < 0 else "JOINT ") + names[j],
            pad + "{",
            pad + f"\tOFFSET {ox:.6f} {oy:.6f} {oz:.6f}",
        ]
        if with_position[j]:
            lines.append(pad + f"\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}")
            columns.append(baked.position_values[:, j])
        else:
            lines.append(pad + f"\tCHANNELS 3 {rot_channels}")
        columns.append(euler[:, j])
        open_blocks.append(j)
    while open_blocks:
        closed = open_blocks.pop()
        lines.append("\t" * depth_of[closed] + "}")
    return lines, columns


def write_bvh(motion: Motion, path: str | Path, *, rotation_order: str = "ZYX") -> None:
    """Write ``motion`` as a BVH file whose forward kinematics reproduces the motion's joint positions.

    BVH has no rest rotations, so the skeleton's rest rotations are baked in: each OFFSET is the joint's rest
    position relative to its parent in world axes (the written zero pose is the motion's rest pose), and each
    frame's local rotation is ``Rw0_p * r * inv(Rw0_j)`` (``Rw0`` the rest world rotations). World joint
    positions of the written file equal the motion's; written world rotations equal the motion's times the
    inverse rest world rotation (identical when the rest rotations are identity).

    The roots get 6 channels; other joints 3 rotation channels in ``rotation_order`` (intrinsic, e.g. ``"ZYX"``
    is ``Zrotation Yrotation Xrotation``), plus 3 position channels when their translation leaves the rest
    offset in some frame. Leaf joints named ``*_End`` whose translation stays at rest are written as End Sites.
    Whitespace in joint names is replaced by ``_``.
    """
    order = rotation_order.upper()
    if sorted(order) != list(_AXES):
        raise ValueError(f"rotation_order must be a permutation of XYZ, got {rotation_order!r}")
    lines, columns = _hierarchy(motion, _bake(motion), order)
    frame_time = 1.0 / motion.fps
    lines += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {frame_time:.8f}"]
    table = torch.cat(columns, dim=1).numpy() if columns else np.zeros((motion.num_frames, 0))
    buffer = io.StringIO()
    buffer.write("\n".join(lines) + "\n")
    np.savetxt(buffer, table, fmt="%.6f", delimiter=" ")
    Path(path).write_text(buffer.getvalue(), encoding="utf-8")


__all__ = ["BvhNote", "read_bvh", "write_bvh"]
