"""Run the Khronos glTF-Validator (npm ``gltf-validator`` in ``frontend/node_modules``) on a file from tests.

The validator is a development dependency of the frontend: ``npm ci`` in ``frontend/`` installs it. Nothing here
skips silently: a missing ``node`` or ``node_modules`` raises :class:`ValidatorUnavailableError` naming the fix.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(__file__).resolve().parent / "validate_gltf.mjs"
VALIDATOR_PACKAGE = REPO_ROOT / "frontend" / "node_modules" / "gltf-validator"


class ValidatorUnavailableError(RuntimeError):
    """node or the npm package gltf-validator is not installed."""


def _node() -> str:
    node = shutil.which("node")
    if node is None:
        raise ValidatorUnavailableError("node is not on PATH: install Node.js (>= 18) to run the glTF validator")
    if not (VALIDATOR_PACKAGE / "package.json").is_file():
        raise ValidatorUnavailableError(
            f"{VALIDATOR_PACKAGE} is missing: run `npm ci` in {REPO_ROOT / 'frontend'} to install gltf-validator"
        )
    return node


def validate_glb(path: str | Path, timeout: float = 120.0) -> dict[str, Any]:
    """The validator's full JSON report on the glTF or GLB file at ``path``."""
    node = _node()
    proc = subprocess.run([node, str(SCRIPT), str(path)], capture_output=True, text=True, timeout=timeout, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"glTF validator failed on {path} (exit {proc.returncode}): {proc.stderr.strip()}")
    return json.loads(proc.stdout)


def format_issues(report: dict[str, Any]) -> str:
    """One line per issue: severity, code, JSON pointer and message."""
    names = {0: "ERROR", 1: "WARNING", 2: "INFO", 3: "HINT"}
    lines = []
    for m in report.get("issues", {}).get("messages", []):
        lines.append(
            f"{names.get(m.get('severity'), m.get('severity'))} {m.get('code')} {m.get('pointer', '')}: {m.get('message')}"
        )
    return "\n".join(lines)


def assert_valid_glb(path: str | Path, *, max_warnings: int | None = None) -> dict[str, Any]:
    """Validate ``path``; fail (AssertionError listing every issue) on any error, or on more than
    ``max_warnings`` warnings when given. Returns the report."""
    report = validate_glb(path)
    issues = report["issues"]
    text = format_issues(report)
    if text:
        print(f"glTF validator issues for {path}:\n{text}")
    assert issues["numErrors"] == 0, f"{path}: {issues['numErrors']} validator error(s):\n{text}"
    if max_warnings is not None:
        assert issues["numWarnings"] <= max_warnings, f"{path}: {issues['numWarnings']} validator warning(s):\n{text}"
    return report


MANY_SCRIPT = Path(__file__).resolve().parent / "validate_gltf_many.mjs"


def validate_many(paths: list[Path], timeout: float = 1800.0) -> dict[str, dict[str, Any]]:
    """Error/warning counts and the first messages for each file, from one validator process."""
    node = _node()
    proc = subprocess.run(
        [node, str(MANY_SCRIPT), *map(str, paths)], capture_output=True, text=True, timeout=timeout, check=False
    )
    if proc.returncode != 0:
        raise RuntimeError(f"glTF validator failed (exit {proc.returncode}): {proc.stderr.strip()}")
    result: dict[str, dict[str, Any]] = json.loads(proc.stdout)
    return result
