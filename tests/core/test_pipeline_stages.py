"""The stage list, the refinement registry, the per-body cache and the one driver (prepare -> refine)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import torch

from retarget_core import body_cache, pipeline
from retarget_core.jobs import JobInputs
from retarget_core.motion import Motion
from retarget_core.options import RetargetOptions, StageSwitches
from retarget_core.refine import RefineContext, StageOutcome, refinement_stages, resolve_device
from retarget_core.stages import REFINEMENT_STAGE_NAMES, STAGE_NAMES, STAGES

SAMPLES = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples"


def test_stage_switches_follow_the_one_stage_list() -> None:
    assert tuple(StageSwitches.model_fields) == STAGE_NAMES
    assert [i.name for i, _ in refinement_stages()] == list(REFINEMENT_STAGE_NAMES)
    for info, fn in refinement_stages():
        assert (fn is not None) == info.available
    opts = RetargetOptions.model_validate({"stages": {"collisions": False}})
    assert not opts.stages.enabled("collisions") and opts.stages.enabled("contacts")
    assert {s.name: s.default for s in STAGES} == RetargetOptions().stages.model_dump()


def test_every_stage_is_registered_once_with_what_the_pipeline_needs() -> None:
    """The registry is the one list: each refinement stage names a module with ``run``, each stage a progress
    weight and options that exist; the eval's default chain and the progress of a default job follow it."""
    from importlib import import_module

    from retarget_core.evaluation import METHODS
    from retarget_core.stages import FINISH_STEPS, PREPARE_ORDER, PREPARE_STEPS, progress_weight

    for info in STAGES:
        assert info.weight > 0, info.name
        assert set(info.options) <= set(RetargetOptions.model_fields), info.name
        if info.module is not None:
            assert callable(import_module(info.module).run), info.name
    assert set(PREPARE_ORDER) == set(PREPARE_STEPS) | {s.name for s in STAGES if s.module is None}
    assert set(METHODS["full"]) == {s.name for s in STAGES if s.module is not None and s.default}
    default_job = [*PREPARE_ORDER, *METHODS["full"], *FINISH_STEPS]
    assert abs(sum(progress_weight(n) for n in default_job) - 1.0) < 1e-9


def test_device_option_is_validated_and_falls_back() -> None:
    with pytest.raises(ValueError):
        RetargetOptions(device="tpu")
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        assert resolve_device("cuda:0").type == "cpu"


def test_body_cache_second_load_skips_the_grids(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from retarget_core.loading import load_character

    monkeypatch.setenv(body_cache.CACHE_DIR_ENV, str(tmp_path))
    body_cache.clear_memory()
    tgt = load_character(SAMPLES / "characters" / "mh_male_bulky.glb")
    t = time.perf_counter()
    first, cached = body_cache.body_assets(tgt.character, tgt.mapping)
    built_s = time.perf_counter() - t
    assert not cached and len(list(tmp_path.glob("*.pt"))) == 1
    body_cache.clear_memory()  # a new process: only the disk cache is left
    again = load_character(SAMPLES / "characters" / "mh_male_bulky.glb")
    t = time.perf_counter()
    second, cached = body_cache.body_assets(again.character, again.mapping)
    loaded_s = time.perf_counter() - t
    assert cached and second.key == first.key
    assert all(
        (a is None and b is None) or torch.equal(a, b) for a, b in zip(first.sdf.grids, second.sdf.grids, strict=True)
    )
    assert loaded_s < built_s, (loaded_s, built_s)
    assert body_cache.body_assets(again.character, again.mapping)[0] is second  # memory level


def test_refine_runs_the_registered_stages_in_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """The pipeline runs what the registry gives, in its order, switched by the options (stages faked)."""
    from retarget_core.stages import stage_info

    seen: list[str] = []

    def make(name: str):  # type: ignore[no-untyped-def]
        def run(ctx: RefineContext, motion: Motion) -> StageOutcome:
            seen.append(name)
            out = Motion(motion.skeleton, motion.fps, motion.rotations.clone(), motion.translations + 0.01, motion.name)
            return StageOutcome(out, {"frames_changed": motion.num_frames})

        return run

    fake = [(stage_info(n), make(n)) for n in REFINEMENT_STAGE_NAMES]
    monkeypatch.setattr(pipeline, "refinement_stages", lambda: fake)
    inputs = JobInputs(SAMPLES / "motions" / "007_03.bvh", "builtin:male_average",
                       options=RetargetOptions(frame_end=20, stages={"eso": False}))  # fmt: skip
    prepared = pipeline.prepare(inputs)
    result = pipeline.refine(prepared)
    assert seen == [n for n in REFINEMENT_STAGE_NAMES if n != "eso" and stage_info(n).default]
    assert result.stages_run[-len(seen):] == seen
    assert set(result.stage_reports) == set(seen)
    assert torch.allclose(result.after.translations, prepared.before.translations + 0.01 * len(seen))
    assert result.after.num_frames == prepared.before.num_frames == prepared.source_view.num_frames
