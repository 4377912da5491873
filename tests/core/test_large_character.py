"""The generated large character (about 100k vertices in five meshes) through the real pipeline, as the CLI runs
it: the roles of its meshes, a job that succeeds, valid output files (docs/meshes.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from retarget_core.bodies.large_character import write_large_character
from retarget_core.io.gltf_read import read_gltf
from retarget_core.jobs import JobInputs
from retarget_core.loading import load_character
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import run_job

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gltf_validator import assert_valid_glb  # noqa: E402

ROLES = {"Body": "body", "Shirt": "accessory", "EyeLeft": "accessory", "EyeRight": "accessory", "Teeth": "accessory"}


@pytest.fixture(scope="module")
def large_glb(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_large_character(tmp_path_factory.mktemp("large") / "large_character.glb")


def test_the_large_character_has_five_meshes_with_their_roles(large_glb: Path) -> None:
    c = load_character(large_glb).character
    assert 85_000 <= c.num_vertices <= 110_000
    assert {m.name: m.role for m in c.meshes} == ROLES
    assert sum(m.vertices for m in c.meshes) == c.num_vertices
    body = next(m for m in c.meshes if m.name == "Body")
    assert int(c.body_vertices.sum()) == body.vertices


def test_a_short_job_on_the_large_character(large_glb: Path, samples: Path, tmp_path: Path) -> None:
    """20 frames of a sample walk, default chain: the job succeeds, its GLBs are valid and keep every vertex,
    and the metrics JSON names the roles."""
    motion = samples / "motions" / "007_03.bvh"
    out = run_job(JobInputs(motion, large_glb, options=RetargetOptions(frame_end=20)), tmp_path / "out")
    report = json.loads(out.metrics_json.read_text())
    assert {m["name"]: m["role"] for m in report["meshes"]} == ROLES
    assert report["frames"] == report["after"]["summary"]["frames"] > 0
    assert report["after"]["summary"]["penetrating_vertices_percent"] is not None
    assert "collisions" in report["context"]["stages_run"]
    result = read_gltf(out.result_glb)
    assert result.character is not None and result.character.num_vertices == load_character(large_glb).character.num_vertices
    assert result.motions and result.motions[0].num_frames == report["frames"]
    assert_valid_glb(out.result_glb)
