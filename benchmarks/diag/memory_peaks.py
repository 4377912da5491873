"""Where a job's resident memory grows: one job on the generated large character (or ``--target``), a thread
sampling the resident set (``VmRSS``) every ``--every`` seconds and, each time it passes the high-water mark by
``--step`` MB, the main thread's innermost calls in this repository. Prints the steps and writes them as JSON.

    PYTHONPATH=. .venv/bin/python benchmarks/diag/memory_peaks.py [--frames 1000] [--motion CLIP] [-o out.json]
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import REPO, add_output, clip_path, parser, results_dir, write_json  # noqa: E402


def rss_mb() -> float:
    """This process's resident set now, MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def repo_stack(thread_id: int, depth: int) -> list[str]:
    """The innermost ``depth`` calls of thread ``thread_id`` inside this repository, outermost first."""
    frame = sys._current_frames().get(thread_id)
    if frame is None:
        return []
    calls = [f"{Path(f.filename).relative_to(REPO)}:{f.lineno} {f.name}" for f in traceback.extract_stack(frame)
             if f.filename.startswith(str(REPO))]  # fmt: skip
    return calls[-depth:]


def watch(main_id: int, every: float, step: float, depth: int, stop: threading.Event, out: list[dict[str, Any]]) -> None:
    """Sample until ``stop``; append a record to ``out`` at each new high-water mark ``step`` MB above the last,
    with the lowest resident set since the record before (what was held between two peaks)."""
    start, mark, low = time.perf_counter(), 0.0, float("inf")
    while not stop.is_set():
        now = rss_mb()
        low = min(low, now)
        if now >= mark + step:
            mark = now
            out.append({"t_s": round(time.perf_counter() - start, 2), "rss_mb": round(now, 1),
                        "low_since_last_mb": round(low, 1), "stack": repo_stack(main_id, depth)})  # fmt: skip
            low = now
        time.sleep(every)


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--motion", type=Path, default=clip_path("001_01"))
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--target", type=Path, default=None, help="a GLB (default: the generated large character)")
    ap.add_argument("--every", type=float, default=0.01, help="seconds between samples")
    ap.add_argument("--step", type=float, default=25.0, help="MB above the last record for a new one")
    ap.add_argument("--depth", type=int, default=6, help="calls kept per record")
    add_output(ap, results_dir("diag") / "memory_peaks.json")
    args = ap.parse_args()
    from retarget_core.bodies.large_character import write_large_character
    from retarget_core.jobs import JobInputs
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import run_job

    records: list[dict[str, Any]] = []
    stop = threading.Event()
    with tempfile.TemporaryDirectory() as tmp:
        glb = args.target or write_large_character(Path(tmp) / "large_character.glb")
        sampler = threading.Thread(target=watch, args=(threading.get_ident(), args.every, args.step, args.depth, stop,
                                                       records), daemon=True)  # fmt: skip
        sampler.start()
        try:
            out = run_job(JobInputs(args.motion, glb, options=RetargetOptions(frame_end=args.frames)), Path(tmp))
        finally:
            stop.set()
            sampler.join()
    for r in records:
        print(f"{r['t_s']:8.2f} s {r['rss_mb']:8.1f} MB (low {r['low_since_last_mb']:8.1f})  " + " <- ".join(reversed(r["stack"][-3:])))
    write_json(args.output, {"motion": args.motion.name, "frames": args.frames, "target": str(args.target or "large"),
                             "stage_s": out.stage_seconds, "peaks": records})  # fmt: skip


if __name__ == "__main__":
    main()
