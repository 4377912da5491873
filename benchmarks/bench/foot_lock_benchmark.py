"""Foot lock: time per frame and the ACCEPTANCE.md feet figures before (copy placed on the floor) and after.

Each clip is first written as a source GLB on mh_male_average (as a studio would send it) and read back; the
judged source labels are taken, as the independent judge does, from the source motion as written (not from
our reader's re-grounded view). Per clip x body: foot lock ms/frame (median of 3 runs, 1 torch thread), the
collision re-check's ms/frame, foot accuracy, skate, float, ground penetration, jerk ratio and end-effector
error before and after, and the stage's own report.

    flock /tmp/heavy.lock python benchmarks/bench/foot_lock_benchmark.py [--clips 007_05:0,001_01:30] \\
        [--bodies mh_male_bulky,mh_female_skinny,mh_neutral_tall] [--frames 300] [-o out.json]

A clip is ``NAME:FPS`` (0 keeps the file's rate; CMU walks here are short: 007_05 has 259 frames at 60 fps).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "core"))

from refine_harness import make_context  # noqa: E402

from retarget_core.copy_retarget import copy_retarget  # noqa: E402
from retarget_core.io.gltf_write import write_glb  # noqa: E402
from retarget_core.loading import load_character, load_motion  # noqa: E402
from retarget_core.metrics.feet_acceptance import feet_figures, planted_feet  # noqa: E402
from retarget_core.motion import Motion  # noqa: E402
from retarget_core.refine import foot_lock  # noqa: E402
from retarget_core.resample import resample  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
END_EFFECTORS = ("LeftHand", "RightHand", "LeftFoot", "RightFoot", "Head")


def jerk(motion: Motion, height: float) -> float:
    """Mean third difference of joint positions, at a 1.80 m body (ACCEPTANCE.md)."""
    _, p = motion.global_transforms()
    p = p * (1.80 / height)
    return float((p[3:] - 3 * p[2:-1] + 3 * p[1:-2] - p[:-3]).norm(dim=-1).mean())


def end_effector_error(motion: Motion, mapping: Any, height: float, source: Motion, s_mapping: Any, s_height: float) -> float:
    """Mean distance (cm at 1.80 m) of hands, feet and head relative to the Hips, result vs source."""
    _, p = motion.global_transforms()
    _, q = source.global_transforms()

    def rel(pos: torch.Tensor, m: Any, h: float) -> torch.Tensor:
        idx = [m.joints[n] for n in END_EFFECTORS]
        return (pos[:, idx] - pos[:, m.joints["Hips"]][:, None]) * (1.80 / h)

    return float((rel(p, mapping, height) - rel(q, s_mapping, s_height)).norm(dim=-1).mean()) * 100.0


def run_case(clip: str, fps: float, frames: int, body_names: list[str], tmp: Path) -> list[dict[str, Any]]:
    average = load_character(SHARED / "characters" / "mh_male_average.glb")
    bvh = load_motion(SHARED / "motions" / "cmu" / f"{clip}.bvh")
    motion = bvh.motion if fps <= 0 else resample(bvh.motion, fps)
    motion = motion.slice(0, frames)
    written = copy_retarget(motion, bvh.mapping, average.character.skeleton, average.mapping)
    path = tmp / f"{clip}_source.glb"
    write_glb(average.character, written, path, clip_name=clip)
    judged = planted_feet(average.character, average.mapping, written)
    source = load_motion(path)
    rows = []
    for name in body_names:
        target = load_character(SHARED / "characters" / f"{name}.glb")
        h = make_context(source, target)
        ctx = h.context
        fast = foot_lock.FootLockParams(check_collisions=False)
        times = []
        for _ in range(3):
            t = time.perf_counter()
            foot_lock.run(ctx, ctx.before, fast)
            times.append(time.perf_counter() - t)
        outcome = foot_lock.run(ctx, ctx.before)
        f = ctx.num_frames
        row: dict[str, Any] = {"clip": clip, "fps": ctx.before.fps, "frames": f, "body": name}
        row["ms_per_frame"] = round(statistics.median(times) * 1000.0 / f, 3)
        row["collision_check_ms_per_frame"] = round(outcome.report["seconds_collision_check"] * 1000.0 / f, 3)
        src_jerk = jerk(written, average.character.height)
        for label, m in (("before", ctx.before), ("after", outcome.motion)):
            figs = feet_figures(target.character, target.mapping, m, judged).as_dict()
            figs["jerk_ratio"] = round(jerk(m, target.character.height) / src_jerk, 4)
            figs["end_effector_error_cm"] = round(
                end_effector_error(m, target.mapping, target.character.height, written, average.mapping,
                                   average.character.height), 3,
            )  # fmt: skip
            row[label] = figs
        row["stage_report"] = outcome.report
        rows.append(row)
        b, a = row["before"], row["after"]
        print(
            f"{clip:7s} {name:17s} {f:4d}f {row['ms_per_frame']:6.3f} ms/f (check {row['collision_check_ms_per_frame']:.1f})"
            f" | acc {b['foot_accuracy']:.3f}->{a['foot_accuracy']:.3f} skate {b['skate_cm']:.2f}->{a['skate_cm']:.2f}"
            f" float {b['float_cm']:.2f}->{a['float_cm']:.2f} gpen {b['ground_penetration_cm']:.2f}->"
            f"{a['ground_penetration_cm']:.2f} jerk {b['jerk_ratio']:.3f}->{a['jerk_ratio']:.3f}"
            f" ee {b['end_effector_error_cm']:.2f}->{a['end_effector_error_cm']:.2f}"
            f" pelvis {outcome.report['pelvis_max_drop_cm']:.1f} cm",
            flush=True,
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clips", default="007_05:0,001_01:30")
    parser.add_argument("--bodies", default="mh_male_bulky,mh_female_skinny,mh_neutral_tall")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("-o", "--output", type=Path, default=REPO / "benchmarks" / "bench" / "results" / "foot_lock_benchmark.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    tmp = Path("/tmp") / "foot_lock_benchmark"
    tmp.mkdir(exist_ok=True)
    rows = []
    for spec in args.clips.split(","):
        clip, _, fps = spec.partition(":")
        rows += run_case(clip, float(fps or 0), args.frames, args.bodies.split(","), tmp)
    result = {
        "benchmark": "foot_lock",
        "machine": {"platform": platform.platform(), "torch": torch.__version__, "threads": torch.get_num_threads()},
        "units": "lengths in cm at a 1.80 m character; speeds per 1/30 s; ms per frame of the stage alone",
        "source": "clip copied on mh_male_average, written as GLB, read back; judged labels from the motion as written",
        "rows": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
