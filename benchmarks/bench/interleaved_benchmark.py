"""Job time of two or more commits on one machine, their runs interleaved round after round.

This shared machine's speed drifts 10-20 % within the hour, so two benchmarks run one after the other can rank
two commits either way. Here each commit gets a worktree (``git worktree add --detach`` in a scratch folder);
each round runs, commit after commit, one fresh process that times, per character (the generated large character
and the bulky sample), a short warm-up job (caches, compiled kernels) and then one ``--frames`` default-chain job
of ``--motion``. The drift falls on every commit alike; the medians over the rounds are compared.

    flock /tmp/heavy.lock python benchmarks/bench/interleaved_benchmark.py BASE NEW [--rounds 3] [--frames 150]
        [-o benchmarks/bench/results/interleaved_benchmark.json]

Prints each run and, per commit, the median whole-job ms/frame of each character and their ratio (issue 20's
targets: the bulky sample's job 20 ms/frame, the large character at most 3 x the bulky sample's time per frame).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    REPO,
    SHARED_DATA,
    add_clip_options,
    add_output,
    machine,
    parser,
    results_dir,
    write_json,
)

CHILD = """
import json, sys, tempfile
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from benchmarks.common import BULKY_SAMPLE, per_frame_ms, run_job_once
from retarget_core.bodies.large_character import write_large_character
motion, frames, fps = Path(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
out = {}
with tempfile.TemporaryDirectory() as tmp:
    large = write_large_character(Path(tmp) / "large_character.glb")
    for name, target in (("large", str(large)), ("bulky", str(BULKY_SAMPLE))):
        run_job_once(motion, target, 30, fps, None)
        out[name] = per_frame_ms(run_job_once(motion, target, frames, fps, None))
print("RESULT " + json.dumps(out))
"""


def timed_round(tree: Path, motion: Path, frames: int, fps: float) -> dict[str, dict[str, float]]:
    """One fresh process of commit ``tree``: per character, its stage and whole-job ms/frame."""
    args = [sys.executable, "-c", CHILD, str(tree), str(motion), str(frames), str(fps)]
    env = {**os.environ, "PYTHONPATH": str(tree), "RETARGET_SHARED_DATA": str(SHARED_DATA)}
    done = subprocess.run(args, cwd=tree, env=env, capture_output=True, text=True, check=False)
    line = next((x for x in done.stdout.splitlines() if x.startswith("RESULT ")), None)
    if done.returncode != 0 or line is None:
        raise SystemExit(f"the job at {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(line[len("RESULT ") :])


def summary(runs: list[dict[str, dict[str, float]]]) -> dict[str, float]:
    """Median whole-job ms/frame per character over the rounds, and the median of the per-round ratios."""
    large = [r["large"]["whole job"] for r in runs]
    bulky = [r["bulky"]["whole job"] for r in runs]
    return {"large_ms_per_frame": statistics.median(large), "bulky_ms_per_frame": statistics.median(bulky),
            "ratio": round(statistics.median(a / b for a, b in zip(large, bulky, strict=True)), 3)}  # fmt: skip


def worktree(commit: str, scratch: Path) -> tuple[str, Path]:
    """A detached worktree of ``commit`` under ``scratch``: (its full hash, its folder)."""
    sha = subprocess.run(
        ["git", "rev-parse", commit], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.strip()
    tree = scratch / sha[:10]
    subprocess.run(["git", "worktree", "add", "--detach", "-f", str(tree), sha], cwd=REPO, check=True,
                   capture_output=True)  # fmt: skip
    return sha, tree


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("commits", nargs="+", help="commits to compare (hashes, branches, HEAD)")
    ap.add_argument("--rounds", type=int, default=3)
    add_clip_options(ap, frames=150, fps=30.0)
    add_output(ap, results_dir("bench") / "interleaved_benchmark.json")
    args = ap.parse_args()
    motion = Path(args.motion)
    runs: dict[str, list[dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        trees = dict(worktree(c, Path(scratch)) for c in args.commits)
        try:
            for r in range(args.rounds):
                for sha, tree in trees.items():
                    runs.setdefault(sha, []).append(timed_round(tree, motion, args.frames, args.fps))
                    last = runs[sha][-1]
                    print(f"round {r + 1} {sha[:10]}: large {last['large']['whole job']:.1f}, "
                          f"bulky {last['bulky']['whole job']:.1f} ms/frame", flush=True)  # fmt: skip
        finally:
            for tree in trees.values():
                subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, check=False)
    medians = {sha: summary(rs) for sha, rs in runs.items()}
    for sha, m in medians.items():
        print(f"{sha[:10]}: large {m['large_ms_per_frame']:.1f}, bulky {m['bulky_ms_per_frame']:.1f} ms/frame, "
              f"ratio {m['ratio']:.2f} x (median of {args.rounds})")  # fmt: skip
    write_json(args.output, {"motion": motion.name, "frames": args.frames, "fps": args.fps, "rounds": args.rounds,
                             "commits": args.commits, "median": medians, "runs": runs, "machine": machine()})  # fmt: skip


if __name__ == "__main__":
    main()
