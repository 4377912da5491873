"""Time a whole job, read to write, stage by stage, as the worker runs it (``pipeline.run_job``).

Defaults: a 300-frame piece (at 30 fps) of CMU 02_08 on the bulky sample body (13,380 vertices). The job is run
``--runs`` times (the first one builds the per-body cache, the others find it warm); the last run's stage times
are reported in ms per frame, for the whole chain and for the copy alone (every refinement stage off).

    python benchmarks/bench/job_benchmark.py [--motion CLIP] [--target BODY] [--frames 300] [-o out.json] [--profile]

``--profile`` also runs one default-chain job (body cache warm) under pyinstrument and writes its call tree
beside the JSON (``<output>_profile.txt``): where the time goes, function by function.

Run it alone (``flock /tmp/heavy.lock``): the machine's two cores are shared, and numbers taken beside another
heavy process mean nothing. CPU seconds are printed beside wall seconds for that reason.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("RETARGET_SHARED_DATA", REPO.parent / "shared" / "data"))
SAMPLES = REPO / "retarget_core" / "data" / "samples"


def run_once(motion: Path, target: str, frames: int, fps: float, stages_on: bool | None) -> dict[str, Any]:
    """One job in a scratch folder: wall and CPU seconds, and the pipeline's seconds per stage.
    ``stages_on``: every refinement stage on (True) or off (False); None: the default chain."""
    from retarget_core.jobs import JobInputs
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import run_job
    from retarget_core.stages import REFINEMENT_STAGE_NAMES

    extra: dict[str, Any] = {} if stages_on is None else {"stages": {n: stages_on for n in REFINEMENT_STAGE_NAMES}}
    opts = RetargetOptions(fps=fps, frame_end=_source_frames(motion, frames, fps), **extra)
    with tempfile.TemporaryDirectory() as tmp:
        start, cpu = time.perf_counter(), time.process_time()
        out = run_job(JobInputs(motion, target, options=opts), Path(tmp))
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        report = json.loads(out.metrics_json.read_text())
    n = report["before"]["summary"]["frames"]
    return {"frames": n, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "stage_s": out.stage_seconds,
            "stage_reports": report["context"].get("stage_reports", {}), "body_cache": report["context"]["body_cache"]}


def _source_frames(motion: Path, frames: int, fps: float) -> int:
    """The source frames that make ``frames`` frames at ``fps``."""
    from retarget_core.loading import load_motion

    src_fps = load_motion(motion).motion.fps
    return max(2, int(round((frames - 1) * src_fps / fps)) + 1)


def per_frame_ms(run: dict[str, Any]) -> dict[str, float]:
    n = run["frames"]
    out = {k: round(1000 * v / n, 2) for k, v in run["stage_s"].items()}
    out["whole job"] = round(1000 * run["wall_s"] / n, 2)
    out["whole job (cpu)"] = round(1000 * run["cpu_s"] / n, 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motion", type=Path, default=DATA / "motions" / "cmu" / "002_08.bvh")
    ap.add_argument("--target", default=str(SAMPLES / "characters" / "mh_male_bulky.glb"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--runs", type=int, default=2, help="jobs per setting; the first one warms the body cache")
    ap.add_argument("-o", "--output", type=Path, default=REPO / "benchmarks" / "bench" / "results" / "job_benchmark.json")
    ap.add_argument("--profile", action="store_true", help="profile one default-chain job (pyinstrument)")
    args = ap.parse_args()
    print(f"job benchmark: {args.motion.name} on {Path(args.target).name}, {args.frames} frames at {args.fps:g} fps, "
          f"torch threads {torch.get_num_threads()} (the pipeline uses its own setting)")  # fmt: skip
    results: dict[str, Any] = {}
    for label, on in (("copy only", False), ("default chain", None), ("every stage", True)):
        runs = [run_once(args.motion, args.target, args.frames, args.fps, on) for _ in range(args.runs)]
        last = runs[-1]
        results[label] = {"runs": runs, "ms_per_frame": per_frame_ms(last)}
        print(f"\n{label} (body cache: {', '.join(r['body_cache'] for r in runs)}):")
        for k, v in results[label]["ms_per_frame"].items():
            print(f"  {k:<20} {v:9.2f} ms/frame")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({
        "motion": args.motion.name, "target": Path(args.target).name, "frames": args.frames, "fps": args.fps,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__},
        "when": time.strftime("%Y-%m-%d %H:%M:%S"), **results,
    }, indent=1))  # fmt: skip
    print(f"\nwrote {args.output}")
    if args.profile:
        profile_job(args.motion, args.target, args.frames, args.fps, args.output.with_name(args.output.stem + "_profile.txt"))


def profile_job(motion: Path, target: str, frames: int, fps: float, out: Path) -> None:
    """One default-chain job under pyinstrument; its call tree (calls under 1 % of the time hidden) to ``out``."""
    from pyinstrument import Profiler

    profiler = Profiler(interval=0.005)
    with profiler:
        run_once(motion, target, frames, fps, None)
    out.write_text(profiler.output_text(unicode=False, color=False, show_all=False, time="seconds"))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
