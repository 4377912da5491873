"""Errors raised by retarget_core. Every message names the file (when known) and the problem."""

from __future__ import annotations


class RetargetError(Exception):
    """Base class of every error this library raises on purpose."""


class InvalidFileError(RetargetError):
    """A file could not be read: wrong type, truncated, malformed, hostile or over a limit."""

    def __init__(self, problem: str, path: str | None = None) -> None:
        self.problem = problem
        self.path = path
        super().__init__(f"{path}: {problem}" if path else problem)


class UnsupportedFileError(InvalidFileError):
    """The file is of a type or uses a feature this library does not read."""


class LimitExceededError(InvalidFileError):
    """The file is over a configured limit (size, frames, joints, vertices)."""


class MappingError(RetargetError):
    """The skeleton could not be mapped to the canonical joints the retargeter needs."""


class ToolMissingError(RetargetError):
    """An external tool (for example the assimp command line) is not installed."""
