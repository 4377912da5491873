"""Where the compiled kernels' time goes: one warm job, each numba kernel's seconds summed per calling chain.

pyinstrument cannot see into a compiled kernel nor, when it runs on a worker thread, who called it: its samples
hang at the top of the call tree. Here every kernel the package imports is wrapped by a timer that reads the Python
stack, so each line of the output is a kernel and the five ``retarget_core`` functions that called it.

    PYTHONPATH=. flock /tmp/heavy.lock python benchmarks/diag/kernel_callers.py [--large] [-o OUT.json]

Default: the job benchmark's case (300 frames of 02_08 on the bulky sample); ``--large``: the generated large
character (``retarget_core.bodies.large_character``). One job builds the caches, the next is timed.
"""

from __future__ import annotations

import collections
import importlib
import pkgutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    BULKY_SAMPLE,
    add_clip_options,
    add_output,
    machine,
    parser,
    results_dir,
    run_job_once,
    write_json,
)

KERNELS: dict[str, tuple[str, ...]] = {
    "retarget_core.geometry.bvh_kernels": ("refit_boxes", "winding_walk", "closest_walk", "indexed_bounds"),
    "retarget_core.contacts.hand_distance_kernel": ("block_distances",),
    "retarget_core.geometry.skinning_kernel": ("_skin",),
}
DEPTH = 5  # callers named per line


def _caller_chain() -> str:
    """The innermost ``DEPTH`` package functions on the stack (kernel modules left out), innermost first."""
    frames = [f for f in traceback.extract_stack()[:-2] if "retarget_core" in f.filename and "kernel" not in f.filename]
    return " <- ".join(f"{Path(f.filename).stem}.{f.name}" for f in frames[::-1][:DEPTH])


def _timed(name: str, fn: Callable[..., Any], seconds: collections.Counter[str], on: list[bool]) -> Callable[..., Any]:
    """``fn`` that adds its wall seconds to ``seconds`` under its name and caller chain while ``on[0]``."""

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        if on[0]:
            seconds[f"{name} <- {_caller_chain()}"] += time.perf_counter() - start
        return out

    return wrapper


def wrap_kernels(seconds: collections.Counter[str], on: list[bool]) -> None:
    """Replace every kernel of :data:`KERNELS` by its timed wrapper wherever a package module imported it."""
    import retarget_core

    modules = [importlib.import_module(m.name) for m in pkgutil.walk_packages(retarget_core.__path__, "retarget_core.")
               if not m.name.endswith(".cli")]  # fmt: skip
    for module_name, names in KERNELS.items():
        kernel_module = importlib.import_module(module_name)
        for name in names:
            original = getattr(kernel_module, name)
            wrapped = _timed(name, original, seconds, on)
            for module in modules:
                for attr, value in list(vars(module).items()):
                    if value is original:
                        setattr(module, attr, wrapped)


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--large", action="store_true", help="the generated large character instead of the bulky sample")
    ap.add_argument("--lines", type=int, default=30, help="lines printed")
    add_output(ap, results_dir("diag") / "kernel_callers.json")
    args = ap.parse_args()
    seconds: collections.Counter[str] = collections.Counter()
    on = [False]
    wrap_kernels(seconds, on)
    with tempfile.TemporaryDirectory() as tmp:
        target = str(BULKY_SAMPLE)
        if args.large:
            from retarget_core.bodies.large_character import write_large_character

            target = str(write_large_character(Path(tmp) / "large_character.glb"))
        run_job_once(args.motion, target, args.frames, args.fps, None)
        on[0] = True
        job = run_job_once(args.motion, target, args.frames, args.fps, None)
    print(f"job {job['wall_s']:.1f} s, kernels {sum(seconds.values()):.1f} s")
    rows = [{"seconds": round(v, 3), "kernel <- callers": k} for k, v in seconds.most_common()]
    for row in rows[: args.lines]:
        print(f"{row['seconds']:8.2f}  {row['kernel <- callers']}")
    write_json(args.output, {"motion": args.motion.name, "frames": args.frames, "character": "large" if args.large
                             else BULKY_SAMPLE.name, "job_wall_s": job["wall_s"], "stage_s": job["stage_s"],
                             "kernels": rows, "machine": machine()})  # fmt: skip


if __name__ == "__main__":
    main()
