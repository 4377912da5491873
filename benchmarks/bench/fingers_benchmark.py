"""What the finger clearance stage (``fingers``, last in the default chain) costs and does.

1. Whole jobs, read to write (``pipeline.run_job``), on 300 frames of CMU 002_08 at 30 fps: the default chain
   with and without the stage, on the Quaternius Witch (a real rig with five fingers a hand, ``--rig``) and on the
   bulky MakeHuman body on the Unreal-style rig with fingers (``tests/core/extras_rigs.py``; the bulky sample GLB
   has no finger joints). Each target's first job warms its body cache and is not reported; then one job without
   the stage, one with it: ms per frame, the stage's share and its report.
2. The case the stage is for: ``tests/core/test_fingers_on_thigh.py``'s seated hand on a bulky thigh (the chain
   before the stage, then the stage alone): its report and seconds.

    python benchmarks/bench/fingers_benchmark.py [--rig GLTF] [--frames 300] [-o out.json]

Run it alone (``flock /tmp/heavy.lock``): the machine's two cores are shared.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    SHARED_DATA,
    add_clip_options,
    add_output,
    machine,
    parser,
    per_frame_ms,
    results_dir,
    run_job_once,
    write_json,
)


def job_pair(motion: Path, target: Path, frames: int, fps: float) -> dict[str, Any]:
    """The default chain on ``target`` without and with the finger stage (a warming job first): ms per frame of
    each, the stage's share of the job with it and its report."""
    run_job_once(motion, str(target), frames, fps, None, {"fingers": False})  # warms the body cache
    without = run_job_once(motion, str(target), frames, fps, None, {"fingers": False})
    with_stage = run_job_once(motion, str(target), frames, fps, None)
    ms = {"without the stage": per_frame_ms(without), "with the stage": per_frame_ms(with_stage)}
    whole = {k: v["whole job"] for k, v in ms.items()}
    return {"target": target.name, "ms_per_frame": ms,
            "whole_job_ratio": round(whole["with the stage"] / whole["without the stage"], 3),
            "fingers_ms_per_frame": ms["with the stage"].get("fingers"),
            "report": with_stage["stage_reports"].get("fingers")}  # fmt: skip


def bulky_with_fingers(folder: Path) -> Path:
    """The bulky MakeHuman body on the Unreal-style rig with fingers, written as a GLB in ``folder``."""
    from retarget_core.io.gltf_write import write_glb
    from tests.core.extras_rigs import finger_body

    path = folder / "mh_male_bulky_fingers.glb"
    write_glb(finger_body("male_bulky", "game_engine"), None, path)
    return path


def thigh_case() -> dict[str, Any]:
    """The seated hand on a bulky thigh (``tests/core/test_fingers_on_thigh.py``): the stage alone on the chain's
    result, its report and seconds."""
    from retarget_core.io.gltf_write import write_glb
    from retarget_core.jobs import JobInputs
    from retarget_core.mapping import map_joints
    from retarget_core.measure import torch_threads
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import PIPELINE_THREADS, prepare, refine, refine_context
    from retarget_core.refine import load_stage
    from tests.core.test_fingers_on_thigh import finger_body, hand_on_thigh_motion

    source = finger_body("female_skinny", "mixamo")
    with tempfile.TemporaryDirectory() as tmp:
        write_glb(
            source, hand_on_thigh_motion(source, map_joints(source.skeleton)), Path(tmp) / "s.glb", clip_name="sit"
        )
        write_glb(finger_body("male_bulky", "game_engine"), None, Path(tmp) / "t.glb")
        opts = RetargetOptions(stages={"fingers": False})
        prepared = prepare(JobInputs(Path(tmp) / "s.glb", Path(tmp) / "t.glb", options=opts))
    with torch_threads(PIPELINE_THREADS):  # as a job runs it
        without = refine(prepared).after
        t0 = time.perf_counter()
        outcome = load_stage("fingers")(refine_context(prepared, RetargetOptions()), without)
    return {"frames": without.num_frames, "stage_s": round(time.perf_counter() - t0, 3), "report": outcome.report}


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--rig", type=Path, default=SHARED_DATA / "rigs" / "quaternius_witch.gltf",
                    help="the real rig with fingers")  # fmt: skip
    add_output(ap, results_dir("bench") / "fingers_benchmark.json")
    args = ap.parse_args()
    out: dict[str, Any] = {"motion": args.motion.name, "frames": args.frames, "fps": args.fps,
                           "machine": {**machine(), "torch": torch.__version__}, "jobs": []}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for target in (args.rig, bulky_with_fingers(Path(tmp))):
            out["jobs"].append(job_pair(args.motion, target, args.frames, args.fps))
            j = out["jobs"][-1]
            print(f"{j['target']}: whole job x{j['whole_job_ratio']} with the stage ({j['fingers_ms_per_frame']} "
                  f"ms/frame); {j['report']}", flush=True)  # fmt: skip
    out["thigh_case"] = thigh_case()
    print(f"thigh case: {out['thigh_case']}", flush=True)
    write_json(args.output, out)


if __name__ == "__main__":
    main()
