"""Time a whole job on the generated large character (about 100k vertices in five meshes) and its peak memory.

1. The character is written to a scratch folder (``retarget_core.bodies.large_character``).
2. A ``--frames`` (300) default-chain job of ``--motion`` at 30 fps, run ``--runs`` times (the first builds the
   per-body cache): stage seconds of the last run, in ms per frame, beside the bulky sample's default chain
   (read from ``--bulky`` (benchmarks/bench/results/job_benchmark.json), or run here with ``--run-bulky``).
3. A ``--memory-frames`` (1000) job of ``--memory-motion`` at the clip's own rate in a fresh process: its peak
   resident memory (``VmHWM`` of /proc/self/status: ``ru_maxrss`` would keep the parent's peak across exec).
   ``--runs 0``: only this job, written into the existing JSON's ``memory``.
4. ``--profile``: one warm job under pyinstrument, its call tree next to the JSON.

    flock /tmp/heavy.lock python benchmarks/bench/large_character_benchmark.py [-o out.json]

Targets (issue 20): the whole job at most 3 x the bulky sample's time per frame; peak memory at most 1.5 GB for
1,000 frames.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    BULKY_SAMPLE,
    REPO,
    add_clip_options,
    add_output,
    clip_path,
    machine,
    parser,
    per_frame_ms,
    profile_to,
    results_dir,
    run_job_once,
    write_json,
)

TIME_RATIO_TARGET = 3.0
MEMORY_TARGET_MB = 1536.0


def memory_job(glb: Path, motion: Path, frames: int, chain: str) -> dict[str, Any]:
    """Peak RSS (MB) of a fresh process running one ``frames``-frame job at the clip's rate; ``chain``:
    ``default`` or ``copy`` (every refinement stage off: reading, contacts, body, metrics and writing)."""
    code = (
        "import json, resource, sys, tempfile, time\n"
        "from pathlib import Path\n"
        "from retarget_core.jobs import JobInputs\n"
        "from retarget_core.options import RetargetOptions\n"
        "from retarget_core.pipeline import run_job\n"
        "from retarget_core.stages import REFINEMENT_STAGE_NAMES\n"
        "glb, motion, frames, chain = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), sys.argv[4]\n"
        "extra = {} if chain == 'default' else {'stages': {n: False for n in REFINEMENT_STAGE_NAMES}}\n"
        "with tempfile.TemporaryDirectory() as tmp:\n"
        "    t = time.perf_counter()\n"
        "    out = run_job(JobInputs(motion, glb, options=RetargetOptions(frame_end=frames, **extra)), Path(tmp))\n"
        "    wall = time.perf_counter() - t\n"
        "    n = json.loads(out.metrics_json.read_text())['frames']\n"
        "hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\n"
        "print(json.dumps({'frames': n, 'wall_s': round(wall, 2), 'stage_s': out.stage_seconds,\n"
        "                  'peak_rss_mb': round(int(hwm) / 1024, 1)}))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(glb), str(motion), str(frames), chain], capture_output=True,
                          text=True, cwd=REPO, check=False)  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"the {frames}-frame job failed: {proc.stderr[-2000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["chain"] = chain
    return out


def bulky_reference(args: argparse.Namespace) -> dict[str, Any]:
    """The bulky sample's default chain, ms per frame (run here or read from the job benchmark's JSON)."""
    if args.run_bulky:
        runs = [run_job_once(args.motion, str(BULKY_SAMPLE), args.frames, args.fps, None) for _ in range(2)]
        return {"source": "run here", "ms_per_frame": per_frame_ms(runs[-1])}
    if not args.bulky.is_file():
        raise SystemExit(f"{args.bulky} is missing: run benchmarks/bench/job_benchmark.py or pass --run-bulky")
    data = json.loads(args.bulky.read_text())
    when = data.get("when") or data.get("machine", {}).get("when")
    return {"source": str(args.bulky.resolve().relative_to(REPO)), "when": when,
            "ms_per_frame": data["default chain"]["ms_per_frame"]}  # fmt: skip


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--runs", type=int, default=2, help="timed jobs; the first one builds the body cache")
    ap.add_argument("--memory-motion", type=Path, default=clip_path("001_01"))
    ap.add_argument("--memory-frames", type=int, default=1000, help="0: skip the memory job")
    ap.add_argument("--memory-chain", choices=("default", "copy"), default="default",
                    help="the memory job's stages (copy: every refinement stage off)")
    ap.add_argument("--bulky", type=Path, default=results_dir("bench") / "job_benchmark.json",
                    help="the job benchmark's JSON: the bulky sample's default chain")
    ap.add_argument("--run-bulky", action="store_true", help="time the bulky sample here instead of reading it")
    ap.add_argument("--profile", action="store_true", help="profile one warm job (pyinstrument)")
    add_output(ap, results_dir("bench") / "large_character_benchmark.json")
    args = ap.parse_args()
    from retarget_core.bodies.large_character import write_large_character
    from retarget_core.loading import load_character

    if args.runs == 0:
        memory_only(args)
        return
    with tempfile.TemporaryDirectory() as tmp:
        glb = write_large_character(Path(tmp) / "large_character.glb")
        character = load_character(glb).character
        meshes = [m.as_dict() for m in character.meshes]
        print(f"large character: {character.num_vertices} vertices, {len(meshes)} meshes")
        for m in meshes:
            print(f"  {m['name']:<10} {m['role']:<10} {m['vertices']:>7} vertices  {m['reason']}")
        runs = [run_job_once(args.motion, str(glb), args.frames, args.fps, None) for _ in range(args.runs)]
        large = per_frame_ms(runs[-1])
        print(f"\n{args.frames} frames of {args.motion.name}, default chain (body cache: "
              f"{', '.join(r['body_cache'] for r in runs)}):")  # fmt: skip
        for k, v in large.items():
            print(f"  {k:<20} {v:9.2f} ms/frame")
        memory = memory_job(glb, args.memory_motion, args.memory_frames, args.memory_chain) if args.memory_frames else None
        if args.profile:
            profile_to(args.output.with_name(args.output.stem + "_profile.txt"),
                       lambda: run_job_once(args.motion, str(glb), args.frames, args.fps, None))  # fmt: skip
    bulky = bulky_reference(args)
    ratio = large["whole job"] / bulky["ms_per_frame"]["whole job"]
    out = {
        "motion": args.motion.name, "frames": args.frames, "fps": args.fps,
        "character": {"vertices": character.num_vertices, "triangles": int(character.faces.shape[0]), "meshes": meshes},
        "runs": runs, "ms_per_frame": large, "bulky_sample": bulky,
        "time_ratio_to_bulky": round(ratio, 2), "time_ratio_target": TIME_RATIO_TARGET,
        "memory": memory, "memory_target_mb": MEMORY_TARGET_MB, "machine": machine(),
    }  # fmt: skip
    print(f"\nwhole job {large['whole job']} ms/frame = {ratio:.2f} x the bulky sample's (target {TIME_RATIO_TARGET})")
    if memory:
        print(f"peak memory, {memory['frames']} frames, {memory['chain']} chain: {memory['peak_rss_mb']} MB "
              f"(target {MEMORY_TARGET_MB:.0f})")  # fmt: skip
    write_json(args.output, out)


def memory_only(args: argparse.Namespace) -> None:
    """``--runs 0``: the memory job alone, its result written into the existing JSON."""
    from retarget_core.bodies.large_character import write_large_character

    with tempfile.TemporaryDirectory() as tmp:
        memory = memory_job(write_large_character(Path(tmp) / "large_character.glb"), args.memory_motion,
                            args.memory_frames, args.memory_chain)  # fmt: skip
    data = json.loads(args.output.read_text()) if args.output.is_file() else {}
    data["memory"], data[f"memory_{args.memory_chain}_chain"] = memory, memory
    data["memory_target_mb"] = MEMORY_TARGET_MB
    print(f"peak memory, {memory['frames']} frames, {memory['chain']} chain: {memory['peak_rss_mb']} MB")
    write_json(args.output, data)


if __name__ == "__main__":
    main()
