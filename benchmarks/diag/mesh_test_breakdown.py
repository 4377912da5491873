"""Where the collision stage's posed-torso mesh test (`collision_mesh.find_mesh_pairs`) spends its time: one
whole job (default chain) with the test's inputs recorded, then the recorded frames timed phase by phase
(choosing the tested vertices, posing the torso, building libigl's distance tree, the distance queries, building
the winding-number tree, the winding numbers).

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/diag/mesh_test_breakdown.py [--motion CLIP]
        [--target BODY] [--frames 300] [-o out.json]

Run it alone: the machine's two cores are shared.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    BULKY_SAMPLE,
    add_clip_options,
    add_output,
    parser,
    results_dir,
    run_job_once,
    write_json,
)

PHASES = ("choose tested vertices", "pose torso", "distance tree", "distance queries", "winding tree", "winding numbers")


def record_calls(motion: Path, target: str, frames: int, fps: float) -> tuple[Any, list[tuple[np.ndarray, float]], float]:
    """Run one job with :func:`find_mesh_pairs` recorded: its setup, ``(posed (n, V, 3), reach)`` per call and
    the seconds the calls took in the job."""
    import retarget_core.refine.collision_mesh as cm

    calls: list[tuple[np.ndarray, float]] = []
    seen: dict[str, Any] = {"seconds": 0.0}
    original = cm.find_mesh_pairs

    def recorded(setup: Any, posed: np.ndarray, near: float, reach: float) -> Any:
        t = time.perf_counter()
        out = original(setup, posed, near, reach)
        seen["seconds"] += time.perf_counter() - t
        seen["setup"] = setup
        calls.append((posed.copy(), reach))
        return out

    cm.find_mesh_pairs = recorded
    try:
        run_job_once(motion, target, frames, fps, None)
    finally:
        cm.find_mesh_pairs = original
    return seen.get("setup"), calls, float(seen["seconds"])


def time_phases(setup: Any, calls: list[tuple[np.ndarray, float]]) -> dict[str, Any]:
    """Seconds per phase over every recorded frame, and how many frames, queries and close queries there were."""
    import igl

    from retarget_core.refine.collision_mesh import _frame_queries

    part = setup.body.part("torso")
    sec = dict.fromkeys(PHASES, 0.0)
    counts = {"frames tested": 0, "frames with queries": 0, "queries": 0, "queries near the torso": 0}

    @contextmanager
    def tick(phase: str) -> Iterator[None]:
        t = time.perf_counter()
        yield
        sec[phase] += time.perf_counter() - t

    for posed, reach in calls:
        for p in posed:
            counts["frames tested"] += 1
            with tick(PHASES[0]):
                queries = _frame_queries(setup, p, reach)
            if not queries:
                continue
            counts["frames with queries"] += 1
            with tick(PHASES[1]):
                local = part.posed(p)
            with tick(PHASES[2]):
                tree = igl.AABB()
                tree.init(local, part.faces)
            with tick(PHASES[4]):
                winding = igl.FastWindingNumberBVH()
                winding.init(local, part.faces)
            for q_idx in queries.values():
                q = np.ascontiguousarray(p[q_idx])
                with tick(PHASES[3]):
                    d2, _, _ = tree.squared_distance(local, part.faces, q)
                close = np.ascontiguousarray(q[np.sqrt(d2) < reach])
                with tick(PHASES[5]):
                    winding.winding_number(close)
                counts["queries"] += len(q)
                counts["queries near the torso"] += len(close)
    return {"torso faces": int(len(part.faces)), **counts, "seconds": {k: round(v, 3) for k, v in sec.items()}}


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--target", default=str(BULKY_SAMPLE), help="the target body (GLB, or builtin:<preset>)")
    add_output(ap, results_dir("diag") / "mesh_test_breakdown.json")
    a = ap.parse_args()
    setup, calls, in_job = record_calls(a.motion, a.target, a.frames, a.fps)
    if setup is None:
        print("the mesh test did not run on this job")
        return
    result = {"motion": a.motion.name, "target": Path(a.target).name, "frames": a.frames, "calls": len(calls),
              "seconds in the job": round(in_job, 3), **time_phases(setup, calls)}  # fmt: skip
    for k, v in result.items():
        print(f"{k:>24}: {v}")
    write_json(a.output, result)


if __name__ == "__main__":
    main()
