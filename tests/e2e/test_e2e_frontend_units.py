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


# Fields of the API's answers that the front end reads (frontend/src/pages/*.js), per OpenAPI schema.
FIELDS_READ = {
    "JobOut": ["id", "status", "stage", "progress", "message", "error_kind", "cancel_requested", "attempt",
               "batch_id", "motion_id", "target_character_id", "options", "created_at", "timings", "warnings",
               "results", "links"],
    "Timings": ["run_seconds", "stages"],
    "AssetOut": ["id", "name", "builtin", "format", "size_bytes", "info", "links"],
    "BatchOut": ["id", "name", "status", "total", "counts", "progress", "jobs", "created_at"],
    "KeyInfo": ["name", "key_prefix"],
}  # fmt: skip
RESULT_KEYS = {"result_glb", "before_glb", "source_glb", "metrics_json"}


def _frontend_paths() -> set[str]:
    """Every /v1 path the front end's sources call, with template parts as '*' segments and no query string."""
    import re

    found: set[str] = set()
    for src in (FRONTEND / "src").rglob("*.js"):
        for m in re.finditer(r"[`'\"](/v1/[^`'\"]*)", src.read_text()):
            path = re.sub(r"\$\{[^}]*\}", "*", m.group(1)).split("?")[0].rstrip("/")
            found.add(path)
    return found


def _matches(path: str, pattern: str) -> bool:
    a, b = path.strip("/").split("/"), pattern.strip("/").split("/")
    return len(a) == len(b) and all(x == "*" or x == y or y.startswith("{") for x, y in zip(a, b, strict=True))


def test_frontend_calls_exist_in_the_openapi_document(tmp_path: Path) -> None:
    """The paths and response fields the front end uses are in the service's OpenAPI document (the contract)."""
    pytest.importorskip("fastapi")
    from api.main import create_app
    from api.serialize import RESULT_FILES
    from api.settings import Settings

    spec = create_app(Settings(data_dir=tmp_path, redis_url=None)).openapi()
    paths = list(spec["paths"])
    used = _frontend_paths()
    assert {"/v1/motions", "/v1/characters", "/v1/jobs", "/v1/batches", "/v1/me"} <= used
    missing = [p for p in used if not any(_matches(p, q) for q in paths)]
    assert not missing, f"the front end calls paths the API does not have: {missing}"
    schemas = spec["components"]["schemas"]
    for name, fields in FIELDS_READ.items():
        props = schemas[name]["properties"]
        assert not [f for f in fields if f not in props], f"{name} lacks fields the front end reads"
    assert {key for key, _ in RESULT_FILES.values()} == RESULT_KEYS
    upload = spec["paths"]["/v1/motions"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert "file" in upload["properties"]
