"""BVH reading and writing: real CMU files, hand-made files with known answers, hostile files, round trips."""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path

import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.config import CoreSettings
from retarget_core.errors import InvalidFileError, LimitExceededError, UnsupportedFileError
from retarget_core.io import bvh as bvh_module
from retarget_core.io.bvh import BvhNote, read_bvh, write_bvh
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton


def _motions_dir() -> Path | None:
    import os

    env = os.environ.get("RETARGET_SHARED_DATA")
    here = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    for candidate in [here] + ([Path(env)] if env else []):  # ../shared/data first, then the variable
        if (candidate / "motions").is_dir():
            return candidate / "motions"
    return None


MOTIONS = _motions_dir()
SHARED_BVH = sorted(MOTIONS.glob("*/*.bvh")) if MOTIONS else []


@pytest.fixture
def shared_motions() -> Path:
    if MOTIONS is None:
        pytest.skip("the shared data set (../shared/data/motions or $RETARGET_SHARED_DATA) is not present")
    return MOTIONS


def _write(tmp_path: Path, text: str, name: str = "t.bvh") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _header_facts(path: Path) -> tuple[int, float, int]:
    """Frames, frame time and joint count (ROOT/JOINT/End Site) read from the file's text independently."""
    frames = frame_time = None
    joints = 0
    with open(path) as fh:
        for line in fh:
            words = line.split()
            if not words:
                continue
            if words[0] in ("ROOT", "JOINT", "End"):
                joints += 1
            elif words[0] == "Frames:":
                frames = int(words[1])
            elif words[:2] == ["Frame", "Time:"]:
                frame_time = float(words[2])
                break
    assert frames is not None and frame_time is not None
    return frames, frame_time, joints


# ------------------------------------------------------------------------------------------- real files


@pytest.mark.skipif(not SHARED_BVH, reason="the shared BVH files (../shared/data/motions) are not present")
@pytest.mark.parametrize("path", SHARED_BVH, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shared_files_parse_with_header_frame_count_and_fps(path: Path) -> None:
    frames, frame_time, joints = _header_facts(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # real files must read without notes
        motion = read_bvh(path)
    assert motion.num_frames == frames
    assert motion.fps == pytest.approx(1.0 / frame_time, rel=1e-4)
    assert motion.fps == round(motion.fps)  # 0.016667 -> 60, .0083333 -> 120
    assert motion.skeleton.num_joints == joints
    assert motion.name == path.stem
    assert torch.isfinite(motion.rotations).all() and torch.isfinite(motion.translations).all()
    assert torch.allclose(motion.rotations.norm(dim=-1), torch.ones(()), atol=1e-5)


def test_shared_file_root_translation_is_offset_plus_channels(shared_motions: Path) -> None:
    path = shared_motions / "cmu" / "007_03.bvh"
    text = path.read_text().split("\n")
    offset = [float(v) for v in next(ln for ln in text if ln.strip().startswith("OFFSET")).split()[1:4]]
    motion_at = next(i for i, ln in enumerate(text) if ln.strip() == "MOTION")
    first_row = [float(v) for v in text[motion_at + 3].split()]
    last_row = [float(v) for v in text[motion_at + 2 + _header_facts(path)[0]].split()]
    motion = read_bvh(path)
    assert offset[1] > 100  # this file's root OFFSET is not zero: dropping it would be visible
    expected_first = torch.tensor([o + v for o, v in zip(offset, first_row[:3], strict=True)])
    expected_last = torch.tensor([o + v for o, v in zip(offset, last_row[:3], strict=True)])
    assert torch.allclose(motion.translations[0, 0], expected_first, atol=1e-4)
    assert torch.allclose(motion.translations[-1, 0], expected_last, atol=1e-4)
    # Root rotation channels Zrotation Yrotation Xrotation of the first frame.
    z, y, x = first_row[3:6]
    expected = rot.from_euler("ZYX", torch.tensor([z, y, x], dtype=torch.float64)).float()
    assert torch.allclose(rot.normalize(motion.rotations[0, 0]), rot.normalize(expected), atol=1e-6)
    # Non-root joints repeat their OFFSET.
    assert torch.equal(motion.translations[:, 1], motion.skeleton.rest_translations[1].expand(motion.num_frames, 3))


def test_largest_shared_file_parses_whole(shared_motions: Path) -> None:
    """The largest shared BVH reads with every frame its header declares and finite values (its time is the
    benchmarks' business, not a test's)."""
    largest = max(shared_motions.glob("*/*.bvh"), key=lambda p: p.stat().st_size)
    declared = int(next(line for line in largest.read_text().splitlines() if line.strip().startswith("Frames:")).split(":")[1])
    motion = read_bvh(largest)
    assert motion.num_frames == declared
    assert bool(torch.isfinite(motion.rotations).all()) and bool(torch.isfinite(motion.translations).all())


# ------------------------------------------------------------------------------------ known answers

CHAIN = """HIERARCHY
ROOT A
{
  OFFSET 10 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT B
  {
    OFFSET 0 1 0
    CHANNELS 2 xROTATION zrotation
    End Site
    {
      OFFSET 0 1 0
    }
  }
  JOINT C
  {
    OFFSET 0 0 2
    CHANNELS 6 Zrotation Xposition Yposition Zposition Xrotation Yrotation
    End Site
    {
      OFFSET 0 0 1
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.5
1 2 3 0 0 0  90 90  0 0 0 0 0 0
0 0 0 90 0 0  0 0  0 5 0 0 0 0
0 0 0 0 0 0  90 0  0 0 0 0 0 0
"""


def _world(motion: Motion) -> torch.Tensor:
    _, pos = motion.global_transforms()
    return pos


def test_channel_order_gives_known_positions(tmp_path: Path) -> None:
    motion = read_bvh(_write(tmp_path, CHAIN))
    names = motion.skeleton.names
    assert names == ["A", "B", "B_End", "C", "C_End"]
    assert motion.skeleton.parents == [-1, 0, 1, 0, 3]
    assert motion.fps == 2.0
    pos = _world(motion)
    a, b, b_end, c, c_end = (names.index(n) for n in names)
    # Frame 0: root at OFFSET + position channels; B "Xrotation Zrotation" 90 90 is Rx(90) * Rz(90):
    # Rz(90) sends +Y to -X, Rx(90) keeps -X. (Rz * Rx would send +Y to +Z.)
    assert torch.allclose(pos[0, a], torch.tensor([11.0, 2.0, 3.0]))
    assert torch.allclose(pos[0, b], torch.tensor([11.0, 3.0, 3.0]))
    assert torch.allclose(pos[0, b_end], torch.tensor([10.0, 3.0, 3.0]), atol=1e-5)
    # Frame 1: root Zrotation 90 turns B's +Y offset into -X; C (6 channels) gets OFFSET + Xposition 5,
    # rotated by the root: (5, 0, 2) -> (0, 5, 2).
    assert torch.allclose(pos[1, b], torch.tensor([9.0, 0.0, 0.0]), atol=1e-5)
    assert torch.allclose(pos[1, b_end], torch.tensor([8.0, 0.0, 0.0]), atol=1e-5)
    assert torch.allclose(motion.translations[1, c], torch.tensor([5.0, 0.0, 2.0]))
    assert torch.allclose(pos[1, c], torch.tensor([10.0, 5.0, 2.0]), atol=1e-5)
    # Frame 2: B Xrotation 90 alone sends +Y to +Z.
    assert torch.allclose(pos[2, b_end], torch.tensor([10.0, 1.0, 1.0]), atol=1e-5)


def test_rotation_channel_order_is_intrinsic_in_file_order(tmp_path: Path) -> None:
    angles = (30.0, -50.0, 70.0)
    for order in ("ZYX", "XYZ", "YXZ", "ZXY"):
        channels = " ".join(f"{axis}rotation" for axis in order)
        text = f"HIERARCHY\nROOT R\n{{\nOFFSET 0 0 0\nCHANNELS 3 {channels}\nEnd Site\n{{\nOFFSET 0 1 0\n}}\n}}\nMOTION\nFrames: 1\nFrame Time: 1\n{angles[0]} {angles[1]} {angles[2]}\n"
        got = read_bvh(_write(tmp_path, text)).rotations[0, 0].double()
        matrix = torch.eye(3, dtype=torch.float64)
        for axis, angle in zip(order, angles, strict=True):
            c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
            i = "XYZ".index(axis)
            j, k = (i + 1) % 3, (i + 2) % 3
            r = torch.eye(3, dtype=torch.float64)
            r[j, j], r[j, k], r[k, j], r[k, k] = c, -s, s, c
            matrix = matrix @ r  # intrinsic: R = R_first * R_second * R_third
        assert torch.allclose(rot.to_matrix(got), matrix, atol=1e-6), order


def test_end_sites_are_static_leaf_joints(tmp_path: Path) -> None:
    motion = read_bvh(_write(tmp_path, CHAIN))
    skeleton = motion.skeleton
    for name, offset in (("B_End", [0.0, 1.0, 0.0]), ("C_End", [0.0, 0.0, 1.0])):
        j = skeleton.index(name)
        assert skeleton.children(j) == []
        assert torch.equal(skeleton.rest_translations[j], torch.tensor(offset))
        assert torch.equal(motion.translations[:, j], torch.tensor(offset).expand(3, 3))
        assert torch.equal(motion.rotations[:, j], rot.identity(3))
    assert torch.equal(skeleton.rest_rotations, rot.identity(5))


def test_joint_without_channels_and_windows_line_ends(tmp_path: Path) -> None:
    text = """HIERARCHY
ROOT A
{
  OFFSET 0 0 0
  CHANNELS 3 Xposition Yposition Zposition
  JOINT B
  {
    OFFSET 0 1 0
    CHANNELS 0
    JOINT C
    {
      OFFSET 0 0 2
      CHANNELS 1 Yrotation
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
1 2 3 0
0 0 0 90
"""
    path = tmp_path / "crlf.bvh"
    path.write_bytes(text.replace("\n", "\r\n").encode())
    motion = read_bvh(path)
    assert motion.fps == 30.0
    assert torch.equal(motion.rotations[:, 0], rot.identity(2))  # position channels only
    assert torch.equal(motion.rotations[:, 1], rot.identity(2))  # no channels
    assert torch.allclose(_world(motion)[0, 2], torch.tensor([1.0, 3.0, 5.0]))
    c_rot = rot.to_matrix(motion.rotations[1, 2])
    assert torch.allclose(c_rot @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)


def test_duplicate_names_made_unique_with_a_note(tmp_path: Path) -> None:
    text = CHAIN.replace("JOINT C", "JOINT B")
    with pytest.warns(BvhNote, match="duplicate joint name 'B'"):
        motion = read_bvh(_write(tmp_path, text))
    assert motion.skeleton.names == ["A", "B", "B_End", "B_2", "B_2_End"]


# ------------------------------------------------------------------------------------------ hostile files


def _replace_motion(rows: str, frames: str = "3", frame_time: str = "0.5") -> str:
    head = CHAIN.split("MOTION")[0]
    return f"{head}MOTION\nFrames: {frames}\nFrame Time: {frame_time}\n{rows}"


ROWS = "\n".join(CHAIN.split("Frame Time: 0.5\n")[1].strip().split("\n"))

HOSTILE = {
    "empty": ("", InvalidFileError, "empty"),
    "not bvh": ("hello world\n", InvalidFileError, "HIERARCHY"),
    "truncated hierarchy": (CHAIN[: CHAIN.index("JOINT C")], InvalidFileError, "ends inside joint 'A'"),
    "missing motion": (CHAIN.split("MOTION")[0], InvalidFileError, "no MOTION"),
    "missing frames line": (CHAIN.split("Frames")[0], InvalidFileError, "Frames"),
    "fewer rows": (
        _replace_motion(ROWS, frames="5"),
        InvalidFileError,
        "declares 5 frames but the MOTION section holds 3",
    ),
    "partial last row": (
        _replace_motion(ROWS + "\n1 2 3", frames="4"),
        InvalidFileError,
        r"frame 4 \(line 31\) has 3 values, expected 14",
    ),
    "nan value": (
        _replace_motion(ROWS.replace("90 90", "nan 90", 1)),
        InvalidFileError,
        "frame 1: channel Xrotation of joint 'B' is nan",
    ),
    "inf value": (
        _replace_motion(ROWS.replace("0 5 0", "0 inf 0", 1)),
        InvalidFileError,
        "frame 2: channel Xposition of joint 'C' is inf",
    ),
    "text value": (
        _replace_motion(ROWS.replace("90 90", "90 abc", 1)),
        InvalidFileError,
        "value 'abc' is not a number",
    ),
    "nan offset": (CHAIN.replace("OFFSET 0 1 0", "OFFSET 0 nan 0", 1), InvalidFileError, "OFFSET value is nan"),
    "huge frame count": (_replace_motion(ROWS, frames="1000000000000"), LimitExceededError, "max_frames"),
    "big frame count, little data": (_replace_motion(ROWS, frames="99999"), InvalidFileError, "holds 3"),
    "negative frame count": (_replace_motion(ROWS, frames="-3"), InvalidFileError, "not a whole number"),
    "zero frame time": (_replace_motion(ROWS, frame_time="0"), InvalidFileError, "frame time must be a positive"),
    "negative frame time": (
        _replace_motion(ROWS, frame_time="-0.1"),
        InvalidFileError,
        "frame time must be a positive",
    ),
    "nan frame time": (_replace_motion(ROWS, frame_time="nan"), InvalidFileError, "frame time must be a positive"),
    "unknown channel": (CHAIN.replace("zrotation", "Xscale"), UnsupportedFileError, "unsupported channel 'Xscale'"),
    "channel count mismatch": (
        CHAIN.replace("CHANNELS 2", "CHANNELS 3"),
        UnsupportedFileError,
        "unsupported channel 'End'",
    ),
    "repeated channel": (
        CHAIN.replace("xROTATION zrotation", "Xrotation xrotation"),
        InvalidFileError,
        "repeats a channel",
    ),
    "missing offset": (CHAIN.replace("OFFSET 0 0 2\n", ""), InvalidFileError, "joint 'C' has no OFFSET"),
    "stray brace": (CHAIN.replace("MOTION", "}\nMOTION"), InvalidFileError, "without an open joint"),
    "long hierarchy line": ("HIERARCHY\nROOT " + "x" * 200_000, InvalidFileError, "longer than"),
    "long data line": (
        _replace_motion(ROWS + "\n" + "1 " * 100_000),
        InvalidFileError,
        "too many for a frame of 14 values",
    ),
    "many blank data lines": (_replace_motion(ROWS + "\n" * 1000), InvalidFileError, "lines for 3 declared frames"),
}


@pytest.mark.timeout(10)
@pytest.mark.parametrize("case", list(HOSTILE), ids=list(HOSTILE))
def test_hostile_files_raise_clear_errors_quickly(tmp_path: Path, case: str) -> None:
    text, error, message = HOSTILE[case]
    path = _write(tmp_path, text)
    start = time.perf_counter()
    with pytest.raises(error, match=message) as info:
        read_bvh(path)
    print(f"{case}: {time.perf_counter() - start:.3f} s")
    assert str(path) in str(info.value)


def test_rows_after_declared_frames_are_dropped_with_a_note(tmp_path: Path) -> None:
    with pytest.warns(BvhNote, match="rows after the 2 declared frames"):
        motion = read_bvh(_write(tmp_path, _replace_motion(ROWS, frames="2")))
    assert motion.num_frames == 2


@pytest.mark.timeout(10)
def test_too_many_joints(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bvh_module, "get_settings", lambda: CoreSettings(max_joints=4))
    with pytest.raises(LimitExceededError, match="more than 4 joints"):
        read_bvh(_write(tmp_path, CHAIN))


@pytest.mark.timeout(10)
def test_joint_name_over_the_limit_is_refused_naming_it(tmp_path: Path) -> None:
    limit = bvh_module.MAX_JOINT_NAME_CHARS
    longest = read_bvh(_write(tmp_path, CHAIN.replace("JOINT B", "JOINT " + "B" * limit), "ok.bvh"))
    assert longest.skeleton.names[1] == "B" * limit
    with pytest.raises(LimitExceededError, match=f"60000 characters .*limit is {limit}, MAX_JOINT_NAME_CHARS"):
        read_bvh(_write(tmp_path, CHAIN.replace("JOINT B", "JOINT " + "B" * 60_000)))  # the timeout is the bound
    spaced = "JOINT " + " ".join(["b"] * (limit // 2 + 1))  # tokens joined by spaces count with their spaces
    with pytest.raises(LimitExceededError, match=f"{limit + 1} characters"):
        read_bvh(_write(tmp_path, CHAIN.replace("JOINT B", spaced)))


@pytest.mark.timeout(10)
def test_deep_nesting_hits_the_joint_limit_without_recursion(tmp_path: Path) -> None:
    depth = 20_000
    text = "HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\n" + "JOINT j\n{\nOFFSET 0 1 0\nCHANNELS 1 Xrotation\n" * depth
    start = time.perf_counter()
    with pytest.raises(LimitExceededError, match="max_joints"):
        read_bvh(_write(tmp_path, text))
    print(f"20,000 nested joints refused in {time.perf_counter() - start:.3f} s")


def test_file_size_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bvh_module, "get_settings", lambda: CoreSettings(max_file_bytes=100))
    with pytest.raises(LimitExceededError, match="max_file_bytes"):
        read_bvh(_write(tmp_path, CHAIN))


def test_frames_times_joints_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bvh_module, "get_settings", lambda: CoreSettings(max_accessor_elements=10))
    with pytest.raises(LimitExceededError, match="3 frames x 5 joints"):
        read_bvh(_write(tmp_path, CHAIN))


# -------------------------------------------------------------------------------------------- round trips


def test_round_trip_of_shared_file(shared_motions: Path, tmp_path: Path) -> None:
    for source in (shared_motions / "cmu" / "007_03.bvh", shared_motions / "cmu_mb" / "01_01.bvh"):
        motion = read_bvh(source)
        out = tmp_path / source.name
        write_bvh(motion, out)
        back = read_bvh(out)
        assert back.skeleton.names == motion.skeleton.names
        assert back.skeleton.parents == motion.skeleton.parents
        assert back.num_frames == motion.num_frames and back.fps == motion.fps
        assert (_world(back) - _world(motion)).abs().max() < 1e-4  # file units (cm / CMU units)


def _random_motion(parents: list[int], frames: int, seed: int) -> Motion:
    gen = torch.Generator().manual_seed(seed)
    joints = len(parents)
    names = [f"j{k}" for k in range(joints)]
    for j in range(joints):
        if parents[j] >= 0 and j not in parents:
            names[j] = names[parents[j]] + "_End"
    rest_rot = rot.normalize(torch.randn(joints, 4, generator=gen))
    rest_trans = torch.randn(joints, 3, generator=gen)
    skeleton = Skeleton(names, parents, rest_trans, rest_rot)
    rotations = rot.normalize(torch.randn(frames, joints, 4, generator=gen))
    translations = rest_trans.expand(frames, joints, 3).clone()
    translations[:, 0] += torch.randn(frames, 3, generator=gen)
    return Motion(skeleton, 24.0, rotations, translations, "random")


def test_round_trip_bakes_rest_rotations(tmp_path: Path) -> None:
    parents = [-1, 0, 0, 1, 2, 3, 4, 1]  # not depth-first: j2 is written after j1's subtree
    motion = _random_motion(parents, frames=7, seed=1)
    motion.translations[:, 2] += torch.randn(7, 3)  # an animated non-root translation needs position channels
    path = tmp_path / "random.bvh"
    write_bvh(motion, path, rotation_order="xzy")
    text = path.read_text()
    assert "CHANNELS 6 Xposition Yposition Zposition Xrotation Zrotation Yrotation" in text
    assert text.count("End Site") == 3  # j5_End, j6_End, j7_End: leaves named *_End
    back = read_bvh(path)
    assert back.fps == 24.0
    assert sorted(back.skeleton.names) == sorted(motion.skeleton.names)
    order = [back.skeleton.index(n) for n in motion.skeleton.names]
    grot, gpos = motion.global_transforms()
    brot, bpos = back.global_transforms()
    assert torch.allclose(bpos[:, order], gpos, atol=1e-4)
    # Written world rotations are the motion's relative to its rest world rotations.
    rest_rot, _ = motion.skeleton.rest_global()
    moving = [j for j, n in enumerate(motion.skeleton.names) if not n.endswith("_End")]
    expected = rot.mul(grot, rot.inv(rest_rot))[:, moving]
    got = brot[:, [order[j] for j in moving]]
    assert torch.allclose(rot.normalize(got), rot.normalize(expected), atol=1e-4)
    # The written zero pose is the motion's rest pose.
    _, rest_pos = motion.skeleton.rest_global()
    _, back_rest = back.skeleton.rest_global()
    assert torch.allclose(back_rest[order], rest_pos, atol=1e-5)


def test_writer_refuses_bad_rotation_order(tmp_path: Path) -> None:
    motion = _random_motion([-1, 0], frames=2, seed=2)
    with pytest.raises(ValueError, match="permutation"):
        write_bvh(motion, tmp_path / "x.bvh", rotation_order="XXY")
