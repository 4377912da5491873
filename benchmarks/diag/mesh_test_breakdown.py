"""Where the collision stage's posed-torso mesh test (`collision_mesh.find_mesh_pairs`) spends its time: one
whole job (default chain) with the test's inputs recorded, then the recorded calls timed phase by phase
(choosing the tested vertices, posing the torso, refitting its tree, the closest triangles, the winding numbers),
and, for comparison, building libigl's distance and winding-number trees on every frame (the test's former way).

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

PHASES = ("choose tested vertices", "pose torso", "refit tree", "closest triangles", "winding numbers",
          "for comparison: libigl's two trees per frame")  # fmt: skip


def record_calls(motion: Path, target: str, frames: int, fps: float) -> tuple[Any, list[tuple[np.ndarray, float, float]], float]:
    """Run one job with :func:`find_mesh_pairs` recorded: its setup, ``(posed (n, V, 3), near, reach)`` per call and
    the seconds the calls took in the job."""
    import retarget_core.refine.collision_mesh as cm

    calls: list[tuple[np.ndarray, float, float]] = []
    seen: dict[str, Any] = {"seconds": 0.0}
    original = cm.find_mesh_pairs

    def recorded(setup: Any, posed: np.ndarray, near: float, reach: float) -> Any:
        t = time.perf_counter()
        out = original(setup, posed, near, reach)
        seen["seconds"] += time.perf_counter() - t
        seen["setup"] = setup
        calls.append((posed.copy(), near, reach))
        return out

    cm.find_mesh_pairs = recorded
    try:
        run_job_once(motion, target, frames, fps, None)
    finally:
        cm.find_mesh_pairs = original
    return seen.get("setup"), calls, float(seen["seconds"])


def time_phases(setup: Any, calls: list[tuple[np.ndarray, float, float]]) -> dict[str, Any]:
    """Seconds per phase over every recorded call, how many frames, queries and close queries there were, and
    for comparison what libigl's two trees per frame (the test's former way) take to build on the same frames."""
    import igl
    import torch

    from retarget_core.geometry.triangle_bvh import closest_triangles, refit
    from retarget_core.refine.collision_mesh import _inside, _queries

    part, tree = setup.body.part("torso"), setup.trees["torso"]
    sec = dict.fromkeys(PHASES, 0.0)
    counts = {"frames tested": 0, "queries": 0, "queries inside or within near": 0}

    @contextmanager
    def tick(phase: str) -> Iterator[None]:
        t = time.perf_counter()
        yield
        sec[phase] += time.perf_counter() - t

    for posed, near, reach in calls:
        counts["frames tested"] += len(posed)
        with tick(PHASES[0]):
            frame, vertex = _queries(setup, "torso", posed, reach)
        with tick(PHASES[1]):
            local = torch.from_numpy(part.posed(posed))
        with tick(PHASES[2]):
            boxes = refit(tree, local)
        q = torch.from_numpy(posed[frame.numpy(), vertex.numpy()])
        with tick(PHASES[4]):
            inside = _inside(tree, boxes, frame, q)
        with tick(PHASES[3]):
            _, face = closest_triangles(tree, boxes, frame, q, torch.where(inside, reach, near).to(q.dtype))
        close = face >= 0
        with tick(PHASES[5]):
            for f in torch.unique(frame).tolist():
                igl.AABB().init(local[f].numpy(), part.faces)
                igl.FastWindingNumberBVH().init(local[f].numpy(), part.faces)
        counts["queries"] += len(q)
        counts["queries inside or within near"] += int(close.sum())
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
