"""The front end's own unit tests (frontend/test/*.test.js: metrics reader, routes, timeline, formatting), run by
Node's built-in test runner so that `pytest` covers them too."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

FRONTEND = Path(__file__).resolve().parents[2] / "frontend"


def test_frontend_unit_tests_pass() -> None:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    tests = sorted(str(p.relative_to(FRONTEND)) for p in (FRONTEND / "test").glob("*.test.js"))
    assert tests, "no front-end unit tests found"
    proc = subprocess.run([node, "--test", *tests], cwd=FRONTEND, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "# fail 0" in proc.stdout
