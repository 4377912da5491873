"""FBX input through the assimp command line tool (optional: Debian package ``assimp-utils``).

FBX is a closed format; rather than parse it in-process we let assimp convert it to GLB in a separate process,
confined by a wall-clock timeout (``fbx_timeout_seconds``), an address-space limit (``fbx_memory_bytes``) and a
file-size limit (``max_file_bytes``), inside a temporary directory that is removed afterwards. The GLB is then
read by :func:`retarget_core.io.gltf_read.read_gltf`, so FBX input obeys the same checks as glTF input.

Notes on assimp 5.2 (Debian 12): the format must be given glued to the flag (``-fglb2``; with a space assimp
ignores it and guesses from the extension), and the binary FBX it *writes* cannot be read back by its own
importer ("block offset is out of range"), while its ASCII FBX (``-ffbxa``) and FBX from other tools can.
Units are left as assimp writes them (FBX files in centimetres stay in centimetres); the normalisation stage
measures and converts them.
"""

from __future__ import annotations

import contextlib
import os
import resource
import shutil
import signal
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from retarget_core.config import get_settings
from retarget_core.errors import InvalidFileError, LimitExceededError, ToolMissingError, UnsupportedFileError
from retarget_core.io.formats import detect_format_bytes

if TYPE_CHECKING:
    from retarget_core.io.gltf_read import GltfContents

STDERR_TAIL_CHARS = 2000
"""How much of assimp's output an error message quotes."""


def _limits(memory_bytes: int, file_bytes: int) -> None:
    """Runs in the child before exec: cap its address space and the files it writes; no core dumps."""
    resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    resource.setrlimit(resource.RLIMIT_FSIZE, (file_bytes, file_bytes))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def _tail(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - STDERR_TAIL_CHARS))
            text = fh.read().decode("utf-8", errors="replace")
    except OSError:
        return ""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower()]
    return " | ".join(errors[-5:] or lines[-5:])


def convert_fbx_to_glb(path: str | Path, out_dir: str | Path) -> Path:
    """Convert the FBX file at ``path`` to ``out_dir/output.glb`` with assimp, under the configured limits.

    Raises ToolMissingError when assimp is not installed, InvalidFileError when the file is not FBX or assimp
    fails, times out or is killed (the message quotes assimp's error output), LimitExceededError when the file
    is over ``max_file_bytes``.
    """
    settings = get_settings()
    path = Path(path)
    label = str(path)
    size = path.stat().st_size
    if size > settings.max_file_bytes:
        raise LimitExceededError(f"the file has {size} bytes, over the limit of {settings.max_file_bytes} (setting max_file_bytes)", label)
    with open(path, "rb") as fh:
        head = fh.read(64)
    try:
        kind: str | None = detect_format_bytes(head, label)
    except UnsupportedFileError:
        kind = None
    if kind != "fbx" and (kind is not None or b"FBX" not in head):
        what = f"its content is {kind.upper()}" if kind else "no FBX header in its first bytes"
        raise UnsupportedFileError(f"not an FBX file ({what})", label)

    exe = shutil.which(settings.assimp_command)
    if exe is None:
        raise ToolMissingError(
            f"FBX needs the assimp command line tool (Debian package assimp-utils); {settings.assimp_command!r} "
            "was not found on PATH (setting assimp_command). Convert the file to GLB, or install assimp-utils."
        )

    out_dir = Path(out_dir)
    source = out_dir / "input.fbx"  # a fixed, safe name: no option injection through odd file names
    target = out_dir / "output.glb"
    shutil.copyfile(path, source)
    log = out_dir / "assimp.log"
    memory, file_bytes = settings.fbx_memory_bytes, settings.max_file_bytes
    with open(log, "wb") as log_fh:
        proc = subprocess.Popen(
            [exe, "export", source.name, target.name, "-fglb2"],
            cwd=out_dir,
            stdin=subprocess.DEVNULL,
            stdout=log_fh,
            stderr=subprocess.STDOUT,
            preexec_fn=lambda: _limits(memory, file_bytes),
            start_new_session=True,  # its own process group: a timeout kills everything it started
        )
        try:
            code = proc.wait(timeout=settings.fbx_timeout_seconds)
        except subprocess.TimeoutExpired:
            _kill_group(proc)
            raise InvalidFileError(
                f"assimp did not convert the FBX file within {settings.fbx_timeout_seconds:g} s (setting fbx_timeout_seconds)",
                label,
            ) from None
    if code < 0:
        name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else str(-code)
        raise InvalidFileError(
            f"assimp was killed by {name} while converting the FBX file (memory limit fbx_memory_bytes="
            f"{memory}, file limit max_file_bytes={file_bytes}): {_tail(log)}",
            label,
        )
    if code != 0 or not target.is_file():
        raise InvalidFileError(f"assimp could not read the FBX file (exit code {code}): {_tail(log)}", label)
    return target


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def read_fbx(path: str | Path, *, fps: float | None = None) -> GltfContents:
    """The skinned character and animations of an FBX file, converted by assimp and read as glTF.

    ``fps``: sampling rate of the motions (default: inferred from the keyframes, as for glTF). Raises
    ToolMissingError without assimp, InvalidFileError (or a subclass) for bad, hostile or over-limit files.
    """
    from retarget_core.io.gltf_read import read_gltf  # lazy: the glTF reader pulls in heavier modules

    label = str(path)
    with tempfile.TemporaryDirectory(prefix="retarget-fbx-") as tmp:
        glb = convert_fbx_to_glb(path, tmp)
        try:
            contents = read_gltf(glb, fps=fps)
        except InvalidFileError as exc:
            raise type(exc)(f"after conversion to glTF by assimp: {exc.problem}", label) from exc
    contents.notes.append("converted from FBX to glTF by assimp; units and axes as assimp wrote them")
    return contents


__all__ = ["convert_fbx_to_glb", "read_fbx"]
