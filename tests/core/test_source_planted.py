"""The source's planted feet are read as the judge reads them: in the source file's own coordinates."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from retarget_core.evaluation import source_as_glb
from retarget_core.io.gltf_read import read_gltf
from retarget_core.io.gltf_write import write_glb
from retarget_core.jobs import JobInputs
from retarget_core.metrics.acceptance import load_judged_file, measure_acceptance
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import prepare

SAMPLES = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples"
WALK = SAMPLES / "motions" / "007_03.bvh"
BODY = SAMPLES / "characters" / "mh_female_skinny.glb"


def _raised(src: Path, out: Path, lift_m: float) -> Path:
    """The GLB ``src`` with its roots ``lift_m`` higher in every frame (a clip whose floor is below y = 0)."""
    contents = read_gltf(src)
    assert contents.character is not None
    m = contents.motions[0]
    t = m.translations.clone()
    roots = [j for j, p in enumerate(m.skeleton.parents) if p < 0]
    t[:, roots, 1] += lift_m
    write_glb(contents.character, replace(m, translations=t), out, clip_name=m.name)
    return out


def _judged_planted(path: Path) -> torch.Tensor:
    """``(F, 2)`` the judge's planted labels of a source file (its own coordinates)."""
    return torch.from_numpy(measure_acceptance(*load_judged_file(path)).planted)


def test_source_plants_are_the_judges_also_when_the_file_floats(tmp_path: Path) -> None:
    glb = source_as_glb(WALK, BODY, tmp_path / "walk.glb", 90, 30.0)
    opts = RetargetOptions(fps=30.0)
    standing = prepare(JobInputs(glb, BODY, None, opts))
    assert standing.source_planted is not None and bool(standing.source_planted.any())
    assert torch.equal(standing.source_planted, _judged_planted(glb))
    floating_glb = _raised(glb, tmp_path / "float.glb", 0.06)
    floating = prepare(JobInputs(floating_glb, BODY, None, opts))
    # Re-grounded on loading, the clip stands as before; in the file's coordinates its toes are 6 cm up.
    assert floating.source_planted is not None and not bool(floating.source_planted.any())
    assert torch.equal(floating.source_planted, _judged_planted(floating_glb))


def test_source_toe_heights_are_read_in_the_file_coordinates(tmp_path: Path) -> None:
    """The source toe heights the foot lock keeps a free foot at (above each toe's rest height, m at 1.80 m) are
    read where the judge reads them: a file 6 cm above its floor has its toes 6 cm higher."""
    glb = source_as_glb(WALK, BODY, tmp_path / "walk.glb", 60, 30.0)
    opts = RetargetOptions(fps=30.0)
    standing = prepare(JobInputs(glb, BODY, None, opts))
    floating = prepare(JobInputs(_raised(glb, tmp_path / "float.glb", 0.06), BODY, None, opts))
    low, high = standing.source_toe_heights, floating.source_toe_heights
    assert low is not None and high is not None and low.shape == (60, 2)
    assert bool(torch.isfinite(low).all()) and float(low.amin()) < 0.03  # the walk's toes touch the floor
    lift = 0.06 * 1.80 / standing.source_body.character.height
    torch.testing.assert_close(high - low, torch.full_like(low, lift), atol=1e-4, rtol=0.0)
