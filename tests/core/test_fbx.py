"""FBX input through the assimp command line: real conversions (when assimp is installed) and fake assimp
scripts that check the plumbing, the timeout and the memory limit (these run everywhere)."""

from __future__ import annotations

import os
import shutil
import stat
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import torch
from scipy.spatial import cKDTree

from retarget_core.config import CoreSettings
from retarget_core.errors import InvalidFileError, ToolMissingError, UnsupportedFileError
from retarget_core.io import fbx as fbx_module
from retarget_core.io.fbx import read_fbx

ASSIMP = shutil.which("assimp")
needs_assimp = pytest.mark.skipif(
    ASSIMP is None, reason="the assimp command line tool (Debian assimp-utils) is not installed"
)

FBX_HEADER = b"Kaydara FBX Binary  \x00\x1a\x00"


@pytest.fixture(scope="module")
def shared(shared_data: Path) -> Path:
    return shared_data


def _gltf_reader() -> ModuleType:
    """The glTF reader module; skip (only) when it cannot be imported."""
    try:
        from retarget_core.io import gltf_read
    except ImportError as exc:
        pytest.skip(f"retarget_core.io.gltf_read is not importable yet ({exc})")
    return gltf_read


def _settings(monkeypatch: pytest.MonkeyPatch, **overrides: Any) -> None:
    monkeypatch.setattr(fbx_module, "get_settings", lambda: CoreSettings(**overrides))


def _script(tmp_path: Path, body: str, name: str = "fake-assimp") -> str:
    path = tmp_path / name
    path.write_text(body)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return str(path)


def _assimp_to_fbx(source: Path, target: Path) -> Path:
    """assimp 5.2 cannot read back the binary FBX it writes; its ASCII FBX (-ffbxa) reads fine."""
    import subprocess

    assert ASSIMP is not None
    subprocess.run([ASSIMP, "export", str(source), str(target), "-ffbxa"], check=True, capture_output=True, timeout=120)
    return target


# ---------------------------------------------------------------------------------------- real assimp


@needs_assimp
def test_character_through_fbx_matches_the_glb(shared: Path, tmp_path: Path) -> None:
    gltf_read = _gltf_reader()
    glb = shared / "characters" / "mh_female_average.glb"
    fbx = _assimp_to_fbx(glb, tmp_path / "character.fbx")
    contents = read_fbx(fbx)
    reference = gltf_read.read_gltf(glb).character
    character = contents.character
    assert character is not None and reference is not None
    assert character.skeleton.names == reference.skeleton.names
    assert character.skeleton.parents == reference.skeleton.parents
    assert character.num_vertices == reference.num_vertices
    assert character.faces.shape == reference.faces.shape
    _, rest = character.skeleton.rest_global()
    _, rest_ref = reference.skeleton.rest_global()
    assert torch.allclose(rest, rest_ref, atol=1e-4)
    # assimp reorders vertices: match them by position, both ways, and compare their skinning.
    near, match = cKDTree(reference.vertices.numpy()).query(character.vertices.numpy())
    back, _ = cKDTree(character.vertices.numpy()).query(reference.vertices.numpy())
    assert near.max() < 1e-4 and back.max() < 1e-4
    dense, dense_ref = character.dense_weights(), reference.dense_weights()[torch.from_numpy(match)]
    assert (dense - dense_ref).abs().max() < 1e-3
    assert any("assimp" in note for note in contents.notes)
    assert contents.motions == []


@needs_assimp
def test_animated_fbx_gives_a_motion(shared: Path, tmp_path: Path) -> None:
    _gltf_reader()
    fbx = _assimp_to_fbx(shared / "motions" / "cmu" / "007_03.bvh", tmp_path / "clip.fbx")
    contents = read_fbx(fbx, fps=30.0)
    assert len(contents.motions) == 1
    motion = contents.motions[0]
    assert motion.fps == 30.0 and motion.num_frames > 30
    assert {"CC_Base_L_Calf", "CC_Base_R_Hand", "CC_Base_Head"} <= set(motion.skeleton.names)
    assert torch.isfinite(motion.rotations).all()


@needs_assimp
@pytest.mark.timeout(30)
def test_corrupt_fbx_reports_assimp_error(shared: Path, tmp_path: Path) -> None:
    fbx = _assimp_to_fbx(shared / "characters" / "mh_male_average.glb", tmp_path / "full.fbx")
    broken = tmp_path / "broken.fbx"
    broken.write_bytes(fbx.read_bytes()[:5000])
    with pytest.raises(InvalidFileError, match=r"assimp could not read the FBX file \(exit code \d+\): .*\S"):
        read_fbx(broken)
    garbage = tmp_path / "garbage.fbx"
    garbage.write_bytes(FBX_HEADER + os.urandom(4000))
    with pytest.raises(InvalidFileError, match="assimp could not read"):
        read_fbx(garbage)


# -------------------------------------------------------------------------- checks that need no assimp


def test_missing_assimp_raises_tool_missing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _settings(monkeypatch, assimp_command="assimp-that-does-not-exist-3f9c")
    path = tmp_path / "x.fbx"
    path.write_bytes(FBX_HEADER + b"\x00" * 100)
    with pytest.raises(ToolMissingError, match="assimp-utils"):
        read_fbx(path)


@pytest.mark.parametrize("content", [os.urandom(2000), b"", b"glTF" + b"\x00" * 100, b"HIERARCHY\nROOT a\n"])
def test_non_fbx_content_is_refused_before_assimp(
    tmp_path: Path, content: bytes, monkeypatch: pytest.MonkeyPatch
) -> None:
    _settings(monkeypatch, assimp_command=_script(tmp_path, "#!/bin/sh\necho ran > ran.txt\nexit 1\n"))
    path = tmp_path / "garbage.fbx"
    path.write_bytes(content)
    with pytest.raises(UnsupportedFileError, match="not an FBX file"):
        read_fbx(path)
    assert not (tmp_path / "ran.txt").exists()


def test_file_size_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _settings(monkeypatch, max_file_bytes=50)
    path = tmp_path / "big.fbx"
    path.write_bytes(FBX_HEADER + b"\x00" * 100)
    with pytest.raises(InvalidFileError, match="max_file_bytes"):
        read_fbx(path)


def test_fake_assimp_output_is_read_as_gltf(shared: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _gltf_reader()
    glb = shared / "characters" / "mh_male_skinny.glb"
    script = _script(
        tmp_path,
        "#!/bin/sh\n"
        '[ "$1" = export ] && [ "$2" = input.fbx ] && [ "$3" = output.glb ] && [ "$4" = -fglb2 ] || exit 3\n'
        f'cp "{glb}" "$3"\n',
    )
    _settings(monkeypatch, assimp_command=script)
    path = tmp_path / "-odd name.fbx"
    path.write_bytes(FBX_HEADER)
    contents = read_fbx(path)
    assert contents.character is not None and contents.character.num_vertices > 1000


def test_unreadable_conversion_names_the_fbx(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _gltf_reader()
    _settings(monkeypatch, assimp_command=_script(tmp_path, "#!/bin/sh\nprintf 'glTF-not-really' > \"$3\"\n"))
    path = tmp_path / "x.fbx"
    path.write_bytes(FBX_HEADER)
    with pytest.raises(InvalidFileError, match="after conversion to glTF by assimp") as info:
        read_fbx(path)
    assert info.value.path == str(path)


@pytest.mark.timeout(20)
def test_timeout_kills_assimp_and_its_children(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pid_file = tmp_path / "child.pid"
    script = _script(tmp_path, f"#!/bin/sh\nsleep 30 &\necho $! > {pid_file}\nwait\n")
    _settings(monkeypatch, assimp_command=script, fbx_timeout_seconds=1.0)
    path = tmp_path / "x.fbx"
    path.write_bytes(FBX_HEADER)
    start = time.perf_counter()
    with pytest.raises(InvalidFileError, match="within 1 s"):
        read_fbx(path)
    assert time.perf_counter() - start < 5.0
    child = int(pid_file.read_text())
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and _alive(child):
        time.sleep(0.05)
    assert not _alive(child), "the process assimp started outlived the timeout"


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


@pytest.mark.timeout(30)
def test_memory_limit_applies_to_assimp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    script = _script(tmp_path, f"#!{sys.executable}\nblock = bytearray(2 * 1024**3)\nprint('allocated')\n")
    _settings(monkeypatch, assimp_command=script, fbx_memory_bytes=512 * 1024**2)
    path = tmp_path / "x.fbx"
    path.write_bytes(FBX_HEADER)
    with pytest.raises(InvalidFileError, match="MemoryError"):
        read_fbx(path)
