"""Giving freed memory back to the system between a job's stages.

glibc keeps freed blocks for reuse; with a job's large short-lived arrays (posed frames, tree boxes) spread over
several threads' arenas, a long job's resident set grows to the sum of its stages' peaks instead of the largest
one. ``malloc_trim`` returns the free pages of every arena to the system; it costs a few milliseconds. Elsewhere
than on glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import lru_cache
from typing import Any


@lru_cache(maxsize=1)
def _libc() -> Any | None:
    """The C library when it is glibc (has ``malloc_trim``), else None."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
    except OSError:
        return None
    return libc if hasattr(libc, "malloc_trim") else None


def release_free_memory() -> bool:
    """Return the allocator's free pages to the system; whether anything was returned (False off glibc)."""
    libc = _libc()
    return bool(libc.malloc_trim(0)) if libc is not None else False


__all__ = ["release_free_memory"]
