"""Recognise a file's type by its content, not its name."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from retarget_core.errors import UnsupportedFileError

FileFormat = Literal["bvh", "glb", "gltf", "fbx"]


def detect_format(path: str | Path) -> FileFormat:
    """The format of the file at ``path`` from its first bytes; raises UnsupportedFileError otherwise."""
    with open(path, "rb") as fh:
        head = fh.read(64)
    return detect_format_bytes(head, str(path))


def detect_format_bytes(head: bytes, label: str | None = None) -> FileFormat:
    """The format from the first (at least 32) bytes of a file."""
    if head[:4] == b"glTF":
        return "glb"
    if head.startswith(b"Kaydara FBX Binary"):
        return "fbx"
    text = head.lstrip(b"\xef\xbb\xbf").lstrip()
    if text[:9].upper() == b"HIERARCHY":
        return "bvh"
    if text[:1] == b"{":
        return "gltf"
    if text[:1] == b";" and b"FBX" in head:
        return "fbx"
    if not head:
        raise UnsupportedFileError("the file is empty", label)
    raise UnsupportedFileError(
        "not a recognised file type (expected BVH, glTF 2.0 / GLB or FBX; checked by content, not by name)", label
    )
