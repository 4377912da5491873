"""Messages without server paths or blob names: storage paths and ``<sha256>.<ext>`` names become the name the
user gave the file (or a neutral word)."""

from __future__ import annotations

import re
from typing import Any

_BLOB = re.compile(r"(?:[^\s'\"()]*/)?(?P<sha>[0-9a-f]{64})\.(?:bvh|glb|gltf|fbx)")
_PATH = re.compile(r"(?:/[^\s'\"():]+)+/(?P<name>[^\s'\"():/]+)")


def redact(text: str, names: dict[str, str] | None = None, default: str = "the file") -> str:
    """``text`` with blob paths and names replaced by ``names[sha256]`` (else ``default``) and any other absolute
    path by its last part."""
    names = names or {}

    def blob(m: re.Match[str]) -> str:
        return names.get(m.group("sha"), default)

    text = _BLOB.sub(blob, text)
    return _PATH.sub(lambda m: m.group("name"), text)


def redact_all(value: Any, names: dict[str, str] | None = None, default: str = "the file") -> Any:
    """:func:`redact` applied to every string inside lists and dicts."""
    if isinstance(value, str):
        return redact(value, names, default)
    if isinstance(value, list):
        return [redact_all(v, names, default) for v in value]
    if isinstance(value, dict):
        return {k: redact_all(v, names, default) for k, v in value.items()}
    return value
