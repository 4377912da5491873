"""X-ray renders, before and after, of the worst cases of an evaluation (``retarget eval ... -o DIR``).

Reads ``DIR/eval.json``, ranks the cases of ``--method`` by how many targets they miss, then by their pen %v
ratio to the copy, reruns the worst ``--count`` of them as the evaluation did (the clip sent as a GLB on the
source body, prepared and refined on the body) and draws, with :mod:`render_penetration`, the frame where the
result counts the most penetrating vertices, once for the copy ("before") and once for the result ("after").

    python benchmarks/diag/render_worst_cases.py out/eval-hard -o docs/img/hard --shared-data ../shared/data

Clips and bodies are found by name: the hard split's (``retarget_core/data/heldout_hard.json``), else files named
on the command line with ``--file``. Writes ``before/pen_<clip>_<body>_f<frame>.png`` and the same under ``after/``
and prints one JSON line per render.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import JUDGE_FPS, parser, prepare_case  # noqa: E402
from benchmarks.diag.render_penetration import FOLD_BAND_M, pick_frames, render_frame, rest_geodesic  # noqa: E402
from retarget_core.body_cache import part_sdf_for  # noqa: E402
from retarget_core.evaluation import method_options  # noqa: E402


def worst_cases(eval_json: Path, method: str, count: int) -> list[dict[str, Any]]:
    """The ``count`` rows of ``method`` missing the most targets, ties broken by the pen %v ratio to the copy."""
    table = json.loads(eval_json.read_text())
    copy = {(r["clip"], r["body"]): r for r in table["rows"] if r["method"] == "copy"}
    rows = [r for r in table["rows"] if r["method"] == method]
    if not rows:
        raise SystemExit(f"{eval_json} has no rows of method {method!r}")

    def badness(r: dict[str, Any]) -> tuple[int, float]:
        missed = sum(not ok for ok in r["targets_met"].values())
        base = copy.get((r["clip"], r["body"]), {}).get("values", {}).get("pen_percent") or 0.0
        pen = r["values"].get("pen_percent") or 0.0
        return missed, pen / base if base else pen

    return sorted(rows, key=badness, reverse=True)[:count]


def case_files(clip: str, body: str, shared_data: Path, extra: list[Path]) -> tuple[Path, Path]:
    """The clip's and the body's files: given on the command line by stem, else the hard split's."""
    by_stem = {p.stem: p for p in extra}
    if clip in by_stem and body in by_stem:
        return by_stem[clip], by_stem[body]
    from retarget_core import heldout_hard

    split = heldout_hard.load_hard_split()
    clip_path = by_stem.get(clip) or heldout_hard.clip_file(shared_data, next(c for c in split.clips if c.name == clip))
    stems = {heldout_hard.body_file(shared_data, n, split).stem: n for n in split.body_names()}
    body_path = by_stem.get(body) or heldout_hard.body_file(shared_data, stems[body], split)
    return clip_path, body_path


def render_case(clip: Path, body: Path, method: str, frames: int, source_body: str, out_dir: Path) -> list[dict[str, Any]]:  # fmt: skip
    """Before and after of one case at the frame where "after" counts the most penetrating vertices."""
    from retarget_core.pipeline import refine

    case = prepare_case(clip, str(body), frames, source_body, method)
    prepared = case.prepared
    after = refine(prepared, options=method_options(method, JUDGE_FPS)).after
    tgt = prepared.target
    ch = tgt.character
    parts, sdf = part_sdf_for(ch, tgt.mapping)
    geodesic = rest_geodesic(ch, parts, 2 * FOLD_BAND_M * ch.height / 1.80)
    frame = pick_frames(ch, tgt.mapping, sdf, after, 1)[0]
    return [render_frame(clip.stem, ch, parts, sdf, geodesic, motion, frame, out_dir / label)
            for label, motion in (("before", prepared.before), ("after", after))]  # fmt: skip


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("eval_dir", type=Path, help="the evaluation's output folder (with eval.json)")
    ap.add_argument("-o", "--out-dir", type=Path, required=True, help="where the PNGs go")
    ap.add_argument("--method", default="full", help="the method whose worst cases are drawn")
    ap.add_argument("--count", type=int, default=3)
    ap.add_argument("--shared-data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--file", type=Path, action="append", default=[], help="a clip or body file, found by stem")
    ap.add_argument("--source-body", default="builtin:male_average", help="the body the clips were sent on")
    args = ap.parse_args()
    torch.set_num_threads(2)
    settings = json.loads((args.eval_dir / "eval.json").read_text())["settings"]
    frames = settings.get("max_frames") or 300
    for row in worst_cases(args.eval_dir / "eval.json", args.method, args.count):
        clip, body = case_files(row["clip"], row["body"], args.shared_data, args.file)
        for line in render_case(clip, body, args.method, frames, args.source_body, args.out_dir):
            print(json.dumps({"missed": [k for k, ok in row["targets_met"].items() if not ok], **line}))


if __name__ == "__main__":
    main()
