"""The pipeline and the ``retarget`` command line on shipped samples, including hostile input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from retarget_core.errors import RetargetError
from retarget_core.jobs import JobCanceled, JobInputs
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import run_job

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gltf_validator import assert_valid_glb  # noqa: E402

RETARGET = [sys.executable, "-m", "retarget_core.cli"]


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run([*RETARGET, *args], capture_output=True, text=True, timeout=timeout, env=env, check=False)


def test_run_job_writes_all_outputs(samples: Path, tmp_path: Path) -> None:
    stages: list[tuple[str, float]] = []
    inputs = JobInputs(
        samples / "motions" / "007_03.bvh",
        samples / "characters" / "mh_female_skinny.glb",
        options=RetargetOptions(frame_start=10, frame_end=70, fps=30),
    )
    out = run_job(inputs, tmp_path / "job", progress=lambda s, f: stages.append((s, f)))
    for path in (out.result_glb, out.before_glb, out.source_glb, out.metrics_json):
        assert path is not None and path.is_file()
    assert not list((tmp_path / "job").glob("*.part"))
    for glb in (out.result_glb, out.before_glb, out.source_glb):
        assert_valid_glb(glb)
    metrics = json.loads(out.metrics_json.read_text())
    assert metrics["frames"] == 31  # 60 frames at 60 fps -> 1 s -> 31 frames at 30 fps
    assert metrics["fps"] == 30 and metrics["context"]["source"]["fps"] == 30
    assert metrics["schema_version"] == "1.0"
    assert len(metrics["before"]["series"]["foot_skate"]["values"]) == 31
    assert metrics["context"]["source"]["mapping"]["joints"]["LeftHand"]["joint"] == "CC_Base_L_Hand"
    assert out.summary["before"]["penetration_volume"]["unit"] == "cm^3"
    # The source measured on its own body; what it flags is among the job's warnings and the report's notes.
    assert metrics["source"]["body"] == metrics["context"]["source"]["body"]
    assert set(metrics["source"]["penetrating_vertices_percent_by_part"]) == set(metrics["after"]["summary"]["penetrating_vertices_percent_by_part"])
    assert set(metrics["source"]["warnings"]) <= set(out.warnings) and set(metrics["source"]["warnings"]) <= set(metrics["notes"])
    # Penetrating vertices for the viewer: in range, deeper than the tolerance, listed deepest first per frame.
    pv = metrics["after"]["penetration_vertices"]
    assert len(pv["frame"]) == len(pv["vertex"]) == len(pv["depth"]) > 0
    assert max(pv["frame"]) < 31 and max(pv["vertex"]) < metrics["context"]["target"]["vertices"]
    assert min(pv["depth"]) > 0.2
    first = [d for f, d in zip(pv["frame"], pv["depth"], strict=True) if f == pv["frame"][0]]
    assert first == sorted(first, reverse=True)
    fractions = [f for _, f in stages]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_contact_vertex_pairs_in_metrics(shared_data: Path, tmp_path: Path) -> None:
    """The swordplay two-hand grip: constrained pairs listed on source and target meshes, in range."""
    inputs = JobInputs(shared_data / "motions" / "cmu" / "002_08.bvh", "builtin:male_skinny",
                       options=RetargetOptions(frame_end=150))  # fmt: skip
    out = run_job(inputs, tmp_path / "job")
    metrics = json.loads(out.metrics_json.read_text())
    pairs = metrics["source_contacts"]["vertex_pairs"]
    assert pairs is not None and len(pairs["frame"]) == metrics["source_contacts"]["constraints"] > 0
    assert len({len(v) for v in pairs.values()}) == 1
    assert max(pairs["target_i"] + pairs["target_j"]) < metrics["context"]["target"]["vertices"]
    assert max(pairs["frame"]) < 150


def test_cancel_between_stages(samples: Path, tmp_path: Path) -> None:
    calls = {"n": 0}

    def cancel_after_read() -> bool:
        calls["n"] += 1
        return calls["n"] > 1

    inputs = JobInputs(samples / "motions" / "007_03.bvh", samples / "characters" / "mh_male_bulky.glb")
    with pytest.raises(JobCanceled):
        run_job(inputs, tmp_path / "job", should_cancel=cancel_after_read)
    assert not (tmp_path / "job" / "result.glb").exists()


def test_cli_run_and_inspect(samples: Path, tmp_path: Path) -> None:
    out = tmp_path / "walk.glb"
    proc = _cli("run", str(samples / "motions" / "01_01_first600.bvh"), "builtin:male_average", "-o", str(out),
                "--end", "120", "--metrics", str(tmp_path / "m.json"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stderr and out.is_file()
    assert_valid_glb(out)
    # The command line runs the default chain: stages that are off by default stay off unless switched on.
    from retarget_core.stages import STAGES

    ran = json.loads((tmp_path / "m.json").read_text())["context"]["stages_run"]
    assert [s.name for s in STAGES if s.name in ran] == [s.name for s in STAGES if s.default]
    bvh_out = tmp_path / "walk.bvh"
    proc = _cli("run", str(samples / "motions" / "007_03.bvh"), str(samples / "characters" / "mh_male_bulky.glb"), "-o", str(bvh_out))
    assert proc.returncode == 0, proc.stderr
    assert bvh_out.read_text().startswith("HIERARCHY")
    proc = _cli("inspect", str(samples / "motions" / "007_03.bvh"), "--json")
    info = json.loads(proc.stdout)
    assert info["frames"] == 208 and info["fps"] == 60
    assert info["mapping"]["joints"]["LeftHand"]["joint"] == "CC_Base_L_Hand"
    proc = _cli("inspect", str(samples / "characters" / "mh_male_bulky.glb"))
    assert proc.returncode == 0 and "LeftForeArm" in proc.stdout and "height" in proc.stdout


HOSTILE = {
    "truncated.bvh": b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition",
    "nan.bvh": None,  # built from a sample below
    "empty.glb": b"",
    "notamesh.glb": b"glTF\x02\x00\x00\x00\x10\x00\x00\x00garbage!",
    "text.glb": b"this is just text pretending to be a model",
}


@pytest.mark.timeout(120)
@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_cli_rejects_hostile_files_with_a_clear_error(samples: Path, tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    data = HOSTILE[name]
    if data is None:
        text = (samples / "motions" / "01_01_first600.bvh").read_text().splitlines()
        i = text.index("MOTION") + 3
        text[i] = " ".join(["nan"] + text[i].split()[1:])
        path.write_text("\n".join(text))
    else:
        path.write_bytes(data)
    proc = _cli("run", str(path), str(samples / "characters" / "mh_male_bulky.glb"), "-o", str(tmp_path / "o.glb"))
    assert proc.returncode == 2
    assert "error:" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "o.glb").exists()


def test_target_without_skin_is_refused(samples: Path) -> None:
    from retarget_core.loading import load_character

    with pytest.raises(RetargetError, match="skinned"):
        load_character(samples / "motions" / "007_03.bvh")


def test_cli_eval_writes_the_table(samples: Path, tmp_path: Path) -> None:
    proc = _cli("eval", str(samples / "motions" / "007_03.bvh"), "-b", str(samples / "characters" / "mh_female_skinny.glb"),
                "-b", "builtin:male_bulky", "--max-frames", "30", "-o", str(tmp_path))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    table = json.loads((tmp_path / "eval.json").read_text())
    assert "| copy |" in proc.stdout and (tmp_path / "eval.md").is_file()
    per_body = {g["bodies"]: g["values"]["penetrating_vertices_percent"] for g in table["per_body"]}
    assert per_body["male_bulky"] > per_body["mh_female_skinny"]
    row = table["rows"][0]
    assert row["method"] == "copy" and row["values"]["pen_percent"] is not None and row["targets_met"]
