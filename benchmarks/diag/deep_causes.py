"""Why the frames deeper than 1 cm are deep, case by case (issue 22, item 3): for each held-out case that misses the
frames > 1 cm target in an evaluation table, the copy and the default chain's result through the job metrics'
deep frames (``retarget_core.metrics.deep_frames``: pose / placement / fold), beside the judge's frames > 1 cm.

    PYTHONPATH=. flock /tmp/heavy.lock .venv/bin/python benchmarks/diag/deep_causes.py \\
        benchmarks/eval/results/eval_heldout_300_swivel_kept/eval.json ../shared/data/motions/cmu \\
        --json benchmarks/diag/results/deep_causes.json

Bodies are read from the held-out cache (``retarget_core.heldout.body_paths``); ``--frames`` (300) caps each clip,
sent as a GLB on the average body and resampled to 30 fps, as the held-out evaluation does.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import parser, prepare_case, write_json  # noqa: E402
from retarget_core.heldout import body_paths  # noqa: E402
from retarget_core.metrics.compute import compute_metrics  # noqa: E402
from retarget_core.motion import Motion  # noqa: E402
from retarget_core.pipeline import refine  # noqa: E402


def missed_cases(eval_json: Path) -> list[tuple[str, str]]:
    """``(clip, body)`` of the default chain's rows that miss the frames > 1 cm target."""
    rows = json.loads(eval_json.read_text())["rows"]
    return [(r["clip"], r["body"]) for r in rows if r["method"] == "full" and not r["targets_met"]["frames_over_1cm"]]


def deep_split(case: Any, motion: Motion) -> dict[str, Any]:
    """The job metrics' share of frames deeper than 1 cm and its split by cause, for ``motion`` on the case's body."""
    target = case.prepared.target
    metrics, _ = compute_metrics(target.character, target.mapping, case.prepared.assets.sdf, motion)
    return {
        "deep_frames_percent": metrics.summary.deep_frames_percent,
        **(metrics.summary.deep_frames_percent_by_cause or {}),
    }


def one_case(clip: Path, body: Path, frames: int) -> dict[str, Any]:
    """The copy's and the result's deep frames of one case."""
    case = prepare_case(clip, str(body), frames, "builtin:male_average")
    result = refine(case.prepared)
    return {"clip": clip.stem, "body": body.stem, "copy": deep_split(case, case.prepared.before),
            "full": deep_split(case, result.after)}  # fmt: skip


def main() -> None:
    ap: argparse.ArgumentParser = parser(__doc__)
    ap.add_argument("eval_json", type=Path, help="an evaluation table (eval.json) of the held-out split")
    ap.add_argument("clips", type=Path, help="the folder of the held-out clips (BVH)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    bodies = {p.stem: p for p in body_paths()}
    rows = []
    for clip, body in missed_cases(a.eval_json):
        row = one_case(a.clips / f"{clip}.bvh", bodies[body], a.frames)
        rows.append(row)
        c, f = row["copy"], row["full"]
        print(f"{clip} x {body}: copy {c['deep_frames_percent']} % -> {f['deep_frames_percent']} % deep; "
              f"result pose {f['pose']}, placement {f['placement']}, fold {f['fold']}", flush=True)  # fmt: skip
    if a.json:
        write_json(a.json, {"eval": str(a.eval_json), "frames": a.frames, "rows": rows})


if __name__ == "__main__":
    main()
