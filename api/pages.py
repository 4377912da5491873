"""Bounds of list requests (``limit``, ``offset``)."""

from __future__ import annotations

from fastapi import HTTPException

from api.settings import Settings

MAX_QUERY_INT = 2**62
"""Largest integer a list query accepts at all (larger answers 422, never a database overflow)."""


def page_bounds(limit: int | None, offset: int, settings: Settings) -> tuple[int, int]:
    """The page size to use and the offset; 422 when the offset is over ``max_list_offset``."""
    if offset > settings.max_list_offset:
        raise HTTPException(422, f"offset {offset} is over the limit of {settings.max_list_offset} (setting "
                                 "RETARGET_API_MAX_LIST_OFFSET)")
    return min(limit or settings.page_size_default, settings.page_size_max), offset
