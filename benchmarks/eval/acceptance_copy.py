"""The judge's figures (ACCEPTANCE.md) for the copy baseline on the held-out split.

For every held-out clip (``retarget_core/data/heldout.json``; first ``--max-frames`` frames at 30 fps) the
source view is the clip copied onto its source body (a bare BVH gets the built-in body fitted to its bones,
``source_body.py``; a GLB its own mesh); every held-out body (generated once, cached as GLB) gets the plain
copy (``copy_retarget``); both are measured with ``retarget_core.metrics.acceptance``. Prints one line per
clip x body and the time per frame, and writes ``benchmarks/eval/results/acceptance_copy.json``.

Run it under the heavy-job lock:

    flock /tmp/heavy.lock python benchmarks/eval/acceptance_copy.py
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

from retarget_core import heldout
from retarget_core.copy_retarget import copy_retarget
from retarget_core.loading import LoadedCharacter, load_character
from retarget_core.metrics.acceptance import (
    AcceptanceFigures,
    figures_from_measures,
    measure_acceptance,
    meets_targets,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    JUDGE_FPS,
    SHARED_DATA,
    add_output,
    load_clip,
    parser,
    results_dir,
    source_view,
    write_json,
)

SUMMARY_FIELDS = (
    "pen_percent", "frames_over_1cm_percent", "head_percent", "contact_preservation", "false_contacts",
    "foot_accuracy", "skate_cm", "ground_penetration_cm", "float_cm", "end_effector_error_cm", "jerk_ratio",
)  # fmt: skip
# Targets that do not compare with the copy (the ratio targets are 1 for the copy by definition).
ABSOLUTE_TARGETS = (
    "contact_preservation", "false_contacts", "foot_accuracy", "skate", "ground_penetration", "float", "jerk_ratio",
)  # fmt: skip


def _fmt(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _summary(figs: list[AcceptanceFigures]) -> dict[str, dict[str, float | None]]:
    out: dict[str, dict[str, float | None]] = {}
    for f in SUMMARY_FIELDS:
        vals = [getattr(x, f) for x in figs if getattr(x, f) is not None]
        out[f] = (
            {"mean": statistics.fmean(vals), "min": min(vals), "max": max(vals), "n": len(vals)}
            if vals
            else {"mean": None, "min": None, "max": None, "n": 0}
        )
    return out


def _report(
    args: argparse.Namespace, bodies: list, params: list, sources: dict, cases: list, started: float, complete: bool
) -> dict[str, Any]:
    figs = [AcceptanceFigures(**c["figures"]) for c in cases]
    per_body = {n: _summary([f for c, f in zip(cases, figs, strict=True) if c["body"] == n]) for n, _ in bodies}
    timing = [f.seconds_per_frame for f in figs] + [s["seconds_per_frame"] for s in sources.values()]
    cpu = [f.cpu_seconds_per_frame for f in figs] + [s["cpu_seconds_per_frame"] for s in sources.values()]
    report = {
        "what": "ACCEPTANCE.md figures of the plain copy (copy_retarget) on the held-out split",
        "complete": complete,
        "settings": {"max_frames": args.max_frames, "fps": JUDGE_FPS, "torch_threads": 1},
        "bodies": [{"name": n, **p.model_dump()} for (n, _), p in zip(bodies, params, strict=True)],
        "sources": sources,
        "cases": cases,
        "summary": _summary(figs),
        "per_body": per_body,
        "seconds_per_frame": {"mean": statistics.fmean(timing), "max": max(timing)} if timing else None,
        "cpu_seconds_per_frame": {"mean": statistics.fmean(cpu), "max": max(cpu)} if cpu else None,
        "seconds": round(time.perf_counter() - started, 1),
    }
    write_json(args.output, report, quiet=True)
    return report


HEADER = (
    f"{'clip':>7} {'body':>15} {'pen%v':>6} {'>1cm%':>6} {'head%v':>6} {'keep':>5} {'false':>5} {'foot':>5} "
    f"{'skate':>5} {'gpen':>5} {'float':>5} {'EE cm':>6} {'jerk':>5} {'ms/f':>5} {'cpu':>4}"
)


def _line(clip: str, name: str, fig: AcceptanceFigures) -> str:
    """One printed row of :data:`HEADER`."""
    return (
        f"{clip:>7} {name:>15} {_fmt(fig.pen_percent):>6} {_fmt(fig.frames_over_1cm_percent, 0):>6} "
        f"{_fmt(fig.head_percent):>6} {_fmt(fig.contact_preservation):>5} {_fmt(fig.false_contacts, 3):>5} "
        f"{_fmt(fig.foot_accuracy):>5} {_fmt(fig.skate_cm):>5} {_fmt(fig.ground_penetration_cm):>5} "
        f"{_fmt(fig.float_cm):>5} {_fmt(fig.end_effector_error_cm):>6} {_fmt(fig.jerk_ratio):>5} "
        f"{fig.seconds_per_frame * 1000:>5.0f} {fig.cpu_seconds_per_frame * 1000:>4.0f}"
    )


def measure_clip(path: Path, max_frames: int, bodies: list[tuple[str, LoadedCharacter]]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The source's figures and, per body, the copy's judged figures for one clip (rows printed as they come)."""
    loaded = load_clip(path, JUDGE_FPS, max_frames)
    body, body_map, view = source_view(loaded)
    src = measure_acceptance(body, body_map, view)
    source = {
        "frames": src.num_frames,
        "source_body_height_m": round(body.height, 4),
        "hand_contact_frames": int((src.hand_distance < 0.015).any(axis=(1, 2)).sum()),
        "pen_percent": float((src.pen_count / src.num_vertices).mean() * 100.0),
        "head_percent": float((src.head_count / src.num_vertices).mean() * 100.0),
        "seconds_per_frame": src.seconds / max(src.num_frames, 1),
        "cpu_seconds_per_frame": src.cpu_seconds / max(src.num_frames, 1),
    }
    cases = []
    for name, target in bodies:
        result = copy_retarget(loaded.motion, loaded.mapping, target.character.skeleton, target.mapping)
        fig = figures_from_measures(measure_acceptance(target.character, target.mapping, result), src)
        checks = meets_targets(fig, fig)
        cases.append({"clip": path.stem, "body": name, "figures": fig.model_dump(),
                      "absolute_targets_met": {k: checks[k].met for k in ABSOLUTE_TARGETS}})  # fmt: skip
        print(_line(path.stem, name, fig), flush=True)
    return source, cases


def main(argv: list[str] | None = None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--motions", type=Path, default=SHARED_DATA / "motions" / "cmu", help="folder of the CMU clips")
    ap.add_argument("--max-frames", type=int, default=300, help="first frames of each clip at 30 fps")
    ap.add_argument("--clips", nargs="*", help="a subset of the held-out clips (file stems)")
    ap.add_argument("--bodies", nargs="*", help="a subset of the held-out bodies (names)")
    ap.add_argument("--cache", type=Path, default=None, help="where the held-out bodies are cached as GLB")
    add_output(ap, results_dir("eval") / "acceptance_copy.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()
    split = heldout.load_split()
    params = [p for p in split.bodies if not args.bodies or p.name in args.bodies]
    t = time.perf_counter()
    bodies = [(p.name, load_character(heldout.body_path(p, args.cache))) for p in params]
    print(f"{len(bodies)} held-out bodies ready in {time.perf_counter() - t:.1f} s", flush=True)
    clip_paths = [p for p in heldout.clip_paths(args.motions) if not args.clips or p.stem in args.clips]
    cases: list[dict[str, Any]] = []
    sources: dict[str, dict[str, Any]] = {}
    print(HEADER, flush=True)
    for path in clip_paths:
        sources[path.stem], clip_cases = measure_clip(path, args.max_frames, bodies)
        cases += clip_cases
        _report(args, bodies, params, sources, cases, started, complete=False)  # partial results as they come
    report = _report(args, bodies, params, sources, cases, started, complete=True)
    _print_summary(report)
    print(f"wrote {args.output} ({report['seconds']} s)")
    return 0


def _print_summary(report: dict[str, Any]) -> None:
    """Each figure's range over all cases, and the time per frame (wall and CPU)."""
    s = report["summary"]
    print("\nall cases: " + ", ".join(f"{k} {_fmt(v['min'])}..{_fmt(v['max'])}" for k, v in s.items()))
    wall, cpu = report["seconds_per_frame"], report["cpu_seconds_per_frame"]
    if wall:
        print(f"time per frame: mean {wall['mean'] * 1000:.0f} ms, max {wall['max'] * 1000:.0f} ms wall; "
              f"CPU mean {cpu['mean'] * 1000:.0f} ms, max {cpu['max'] * 1000:.0f} ms")  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
