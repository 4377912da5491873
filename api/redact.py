"""Messages without server paths or blob names: storage paths and ``<sha256>.<ext>`` names become the name the
user gave the file (or a neutral word)."""

from __future__ import annotations

import re
from typing import Any

# Both scans are linear in the text: a blob name is found by its fixed-length digest, then widened back over the
# path before it; a path is one run of path characters starting at a "/" (a pattern that lets a run start
# anywhere in a long token, or nests quantifiers, tries every start: seconds on a 60,000-character joint name).
_BLOB = re.compile(r"(?P<sha>[0-9a-f]{64})\.(?:bvh|glb|gltf|fbx)")
_SEPARATORS = " \t\n\r\f\v'\"()"
_PATH_RUN = re.compile(r"/[^\s'\"():]+")


def _token_start(text: str, end: int, floor: int) -> int:
    """Where the token that ends at ``end`` begins (not before ``floor``)."""
    return max([floor] + [text.rfind(ch, floor, end) + 1 for ch in _SEPARATORS])


def _replace_blobs(text: str, names: dict[str, str], default: str) -> str:
    out: list[str] = []
    done = 0
    for m in _BLOB.finditer(text):
        start = m.start()
        if start > done and text[start - 1] == "/":  # the directory part of a stored path goes too
            start = _token_start(text, start - 1, done)
        out += [text[done:start], names.get(m.group("sha"), default)]
        done = m.end()
    return "".join(out) + text[done:]


def _last_part(m: re.Match[str]) -> str:
    """An absolute path (two parts or more) as its last part; anything else unchanged."""
    run = m.group(0)
    body = run.rstrip("/")
    cut = body.rfind("/")
    return run if cut < 2 else body[cut + 1:] + run[len(body):]


def redact(text: str, names: dict[str, str] | None = None, default: str = "the file") -> str:
    """``text`` with blob paths and names replaced by ``names[sha256]`` (else ``default``) and any other absolute
    path by its last part."""
    return _PATH_RUN.sub(_last_part, _replace_blobs(text, names or {}, default))


def redact_all(value: Any, names: dict[str, str] | None = None, default: str = "the file") -> Any:
    """:func:`redact` applied to every string inside lists and dicts."""
    if isinstance(value, str):
        return redact(value, names, default)
    if isinstance(value, list):
        return [redact_all(v, names, default) for v in value]
    if isinstance(value, dict):
        return {k: redact_all(v, names, default) for k, v in value.items()}
    return value
