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

import statistics
import sys
from pathlib import Path
from typing import Any

import torch

from retarget_core.cases import context_from_files
from retarget_core.copy_retarget import copy_retarget
from retarget_core.io.gltf_write import write_glb
from retarget_core.loading import load_character
from retarget_core.metrics.feet_acceptance import feet_figures, planted_feet
from retarget_core.motion import Motion
from retarget_core.refine import foot_lock

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    REFERENCE_HEIGHT_M,
    add_output,
    character_path,
    clip_path,
    jerk,
    load_clip,
    machine,
    parser,
    results_dir,
    timer,
    write_json,
)

END_EFFECTORS = ("LeftHand", "RightHand", "LeftFoot", "RightFoot", "Head")


def end_effector_error(motion: Motion, mapping: Any, height: float, source: Motion, s_mapping: Any, s_height: float) -> float:
    """Mean distance (cm at 1.80 m) of hands, feet and head relative to the Hips, result vs source."""
    _, p = motion.global_transforms()
    _, q = source.global_transforms()

    def rel(pos: torch.Tensor, m: Any, h: float) -> torch.Tensor:
        idx = [m.joints[n] for n in END_EFFECTORS]
        return (pos[:, idx] - pos[:, m.joints["Hips"]][:, None]) * (REFERENCE_HEIGHT_M / h)

    return float((rel(p, mapping, height) - rel(q, s_mapping, s_height)).norm(dim=-1).mean()) * 100.0


def source_glb(clip: str, fps: float, frames: int, tmp: Path) -> tuple[Path, Any, Motion, Any]:
    """The clip copied onto mh_male_average and written as a GLB (what a studio sends); the path, the average
    body, the motion as written and its judged planted-feet labels (taken from that motion, as the judge does)."""
    average = load_character(character_path("mh_male_average"))
    bvh = load_clip(clip_path(clip), fps, frames)
    written = copy_retarget(bvh.motion, bvh.mapping, average.character.skeleton, average.mapping)
    path = tmp / f"{clip}_source.glb"
    write_glb(average.character, written, path, clip_name=clip)
    return path, average, written, planted_feet(average.character, average.mapping, written)


def run_case(clip: str, fps: float, frames: int, body_names: list[str], tmp: Path) -> list[dict[str, Any]]:
    path, average, written, judged = source_glb(clip, fps, frames, tmp)
    src_jerk = jerk(written, average.character.height)
    rows = []
    for name in body_names:
        ctx = context_from_files(path, character_path(name))
        target = ctx.target
        fast = foot_lock.FootLockParams(check_collisions=False)
        times = []
        for _ in range(3):
            with timer() as took:
                foot_lock.run(ctx, ctx.before, fast)
            times.append(took.wall_s)
        outcome = foot_lock.run(ctx, ctx.before)
        f = ctx.num_frames
        row: dict[str, Any] = {"clip": clip, "fps": ctx.before.fps, "frames": f, "body": name}
        row["ms_per_frame"] = round(statistics.median(times) * 1000.0 / f, 3)
        row["collision_check_ms_per_frame"] = round(outcome.report["seconds_collision_check"] * 1000.0 / f, 3)
        for label, m in (("before", ctx.before), ("after", outcome.motion)):
            figs = feet_figures(target, ctx.target_mapping, m, judged).as_dict()
            figs["jerk_ratio"] = round(jerk(m, target.height) / src_jerk, 4)
            figs["end_effector_error_cm"] = round(
                end_effector_error(m, ctx.target_mapping, target.height, written, average.mapping,
                                   average.character.height), 3,
            )  # fmt: skip
            row[label] = figs
        row["stage_report"] = outcome.report
        rows.append(row)
        print_row(row, outcome.report)
    return rows


def print_row(row: dict[str, Any], report: dict[str, Any]) -> None:
    b, a = row["before"], row["after"]
    print(
        f"{row['clip']:7s} {row['body']:17s} {row['frames']:4d}f {row['ms_per_frame']:6.3f} ms/f (check {row['collision_check_ms_per_frame']:.1f})"
        f" | acc {b['foot_accuracy']:.3f}->{a['foot_accuracy']:.3f} skate {b['skate_cm']:.2f}->{a['skate_cm']:.2f}"
        f" float {b['float_cm']:.2f}->{a['float_cm']:.2f} gpen {b['ground_penetration_cm']:.2f}->"
        f"{a['ground_penetration_cm']:.2f} jerk {b['jerk_ratio']:.3f}->{a['jerk_ratio']:.3f}"
        f" ee {b['end_effector_error_cm']:.2f}->{a['end_effector_error_cm']:.2f}"
        f" pelvis {report['pelvis_max_drop_cm']:.1f} cm",
        flush=True,
    )


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--clips", default="007_05:0,001_01:30", help="NAME:FPS,... (FPS 0: the file's rate)")
    ap.add_argument("--bodies", default="mh_male_bulky,mh_female_skinny,mh_neutral_tall")
    ap.add_argument("--frames", type=int, default=300)
    add_output(ap, results_dir("bench") / "foot_lock_benchmark.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    tmp = Path("/tmp") / "foot_lock_benchmark"
    tmp.mkdir(exist_ok=True)
    rows = []
    for spec in args.clips.split(","):
        clip, _, fps = spec.partition(":")
        rows += run_case(clip, float(fps or 0), args.frames, args.bodies.split(","), tmp)
    write_json(args.output, {
        "benchmark": "foot_lock",
        "machine": {**machine(), "torch": torch.__version__, "threads": torch.get_num_threads()},
        "units": "lengths in cm at a 1.80 m character; speeds per 1/30 s; ms per frame of the stage alone",
        "source": "clip copied on mh_male_average, written as GLB, read back by the pipeline (retarget_core.cases); "
                  "judged labels from the motion as written",
        "rows": rows,
    })  # fmt: skip


if __name__ == "__main__":
    main()
