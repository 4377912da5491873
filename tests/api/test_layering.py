"""The import contracts in .importlinter hold (import-linter, as CI runs it), and they can fail."""

from __future__ import annotations

import configparser
import pkgutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LINT = Path(sys.executable).with_name("lint-imports")
LIGHT = {"errors", "jobs", "options", "stages", "io", "io.formats", "bodies", "bodies.params"}
"""The retarget_core modules the API may import (no torch, no mesh libraries)."""


def lint(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(LINT), "--no-cache", *args], cwd=cwd, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(cwd), "PATH": str(LINT.parent)})


def test_contracts_are_kept() -> None:
    done = lint(REPO)
    assert done.returncode == 0 and " 0 broken" in done.stdout, done.stdout + done.stderr


def test_the_light_api_contract_names_every_heavy_module() -> None:
    import retarget_core

    config = configparser.ConfigParser()
    config.read(REPO / ".importlinter")
    forbidden = set(config["importlinter:contract:api-is-light"]["forbidden_modules"].split())
    modules = {m.name.removeprefix("retarget_core.") for m in pkgutil.walk_packages(retarget_core.__path__,
                                                                                   "retarget_core.")}
    assert modules >= LIGHT

    def covered(name: str) -> bool:
        full = f"retarget_core.{name}"
        return any(full == f or full.startswith(f + ".") for f in forbidden)

    assert sorted(m for m in modules - LIGHT if not covered(m)) == [], \
        "add these to the api-is-light contract, or to LIGHT if they are light"
    assert not any(covered(m) for m in LIGHT)
    assert {"torch", "scipy", "trimesh"} <= forbidden


def test_the_api_starts_without_torch() -> None:
    code = "import sys, api.main, api.services.jobs; print(sorted(m for m in sys.modules if m == 'torch'))"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stdout + done.stderr


def test_a_route_importing_a_route_breaks_the_contract(tmp_path: Path) -> None:
    """The same contract on a tiny package whose one route imports another: lint-imports must say BROKEN."""
    routes = tmp_path / "shop" / "routes"
    routes.mkdir(parents=True)
    (tmp_path / "shop" / "__init__.py").write_text("")
    (routes / "__init__.py").write_text("")
    (routes / "orders.py").write_text("from shop.routes import users\n")
    (routes / "users.py").write_text("")
    config = configparser.ConfigParser()
    config.read(REPO / ".importlinter")
    contract = config["importlinter:contract:routes-independent"]
    (tmp_path / ".importlinter").write_text(
        "[importlinter]\nroot_packages =\n    shop\n\n[importlinter:contract:routes-independent]\n"
        f"name = {contract['name']}\ntype = {contract['type']}\nmodules =\n    shop.routes.*\n")
    done = lint(tmp_path)
    assert done.returncode != 0 and "BROKEN" in done.stdout, done.stdout + done.stderr
    assert "shop.routes.orders -> shop.routes.users" in done.stdout
