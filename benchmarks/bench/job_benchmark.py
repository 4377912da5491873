"""Time a whole job, read to write, stage by stage, as the worker runs it (``pipeline.run_job``).

Defaults: a 300-frame piece (at 30 fps) of CMU 02_08 on the bulky sample body (13,380 vertices). The job is run
``--runs`` times (the first one builds the per-body cache, the others find it warm); the last run's stage times
are reported in ms per frame, for the whole chain and for the copy alone (every refinement stage off).

    python benchmarks/bench/job_benchmark.py [--motion CLIP] [--target BODY] [--frames 300] [-o out.json] [--profile]
        [--default-only --runs 3]

``--default-only`` times the default chain alone (for runs of two versions taken in turn: on a shared machine the
spread between runs an hour apart is 10 %).

``--profile`` also runs one default-chain job (body cache warm) under pyinstrument and writes its call tree
beside the JSON (``<output>_profile.txt``): where the time goes, function by function.

Run it alone (``flock /tmp/heavy.lock``): the machine's two cores are shared, and numbers taken beside another
heavy process mean nothing. CPU seconds are printed beside wall seconds for that reason.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    BULKY_SAMPLE,
    add_clip_options,
    add_output,
    machine,
    parser,
    per_frame_ms,
    profile_to,
    results_dir,
    run_job_once,
    write_json,
)

CHAINS: tuple[tuple[str, bool | None], ...] = (("copy only", False), ("default chain", None), ("every stage", True))
"""What is timed: every refinement stage off, the default chain, every stage on."""


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--target", default=str(BULKY_SAMPLE), help="the target body (GLB, or builtin:<preset>)")
    ap.add_argument("--runs", type=int, default=2, help="jobs per setting; the first one warms the body cache")
    add_output(ap, results_dir("bench") / "job_benchmark.json")
    ap.add_argument("--profile", action="store_true", help="profile one default-chain job (pyinstrument)")
    ap.add_argument("--default-only", action="store_true", help="time the default chain alone")
    args = ap.parse_args()
    print(f"job benchmark: {args.motion.name} on {Path(args.target).name}, {args.frames} frames at {args.fps:g} fps, "
          f"torch threads {torch.get_num_threads()} (the pipeline uses its own setting)")  # fmt: skip
    results: dict[str, Any] = {}
    for label, on in [c for c in CHAINS if c[0] == "default chain" or not args.default_only]:
        runs = [run_job_once(args.motion, args.target, args.frames, args.fps, on) for _ in range(args.runs)]
        results[label] = {"runs": runs, "ms_per_frame": per_frame_ms(runs[-1])}
        print(f"\n{label} (body cache: {', '.join(r['body_cache'] for r in runs)}):")
        for k, v in results[label]["ms_per_frame"].items():
            print(f"  {k:<20} {v:9.2f} ms/frame")
    write_json(args.output, {"motion": args.motion.name, "target": Path(args.target).name, "frames": args.frames,
                             "fps": args.fps, "machine": {**machine(), "torch": torch.__version__}, **results})  # fmt: skip
    if args.profile:
        profile_to(args.output.with_name(args.output.stem + "_profile.txt"),
                   lambda: run_job_once(args.motion, args.target, args.frames, args.fps, None))  # fmt: skip


if __name__ == "__main__":
    main()
