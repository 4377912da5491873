"""Fixtures shared by all tests: where the shared real data and the shipped samples are."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "retarget_core" / "data" / "samples"


def shared_data_dir() -> Path | None:
    """The shared data set (../shared/data beside the repo, or $RETARGET_SHARED_DATA), if present."""
    env = os.environ.get("RETARGET_SHARED_DATA")
    for candidate in ([Path(env)] if env else []) + [REPO.parent / "shared" / "data", REPO.parent.parent / "shared" / "data"]:
        if (candidate / "characters").is_dir():
            return candidate
    return None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if path is None:
        pytest.skip("the shared data set (../shared/data) is not present on this machine")
    return path


@pytest.fixture(scope="session")
def samples() -> Path:
    return SAMPLES


EXPECTED_SKIP = "shared"
"""The only skips a complete machine expects: tests that need ../shared/data when it is absent (their reasons say
"shared"). Any other skip (no PostgreSQL, Redis, Chromium, node, a package) means the set-up is broken."""


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter, exitstatus: int) -> None:
    """List skips that are not expected, and fail the run when there are any (``make test`` installs the rest)."""
    unexpected = [r for r in terminalreporter.stats.get("skipped", [])
                  if EXPECTED_SKIP not in str(getattr(r, "longrepr", "")).lower()]  # fmt: skip
    if not unexpected:
        return
    terminalreporter.section("unexpected skips")
    for r in unexpected:
        terminalreporter.write_line(f"{r.nodeid}: {r.longrepr}")
    terminalreporter._session.exitstatus = pytest.ExitCode.TESTS_FAILED  # type: ignore[attr-defined]
