"""Where a result's pen %v lies, part against part: for one clip x body, the copy and the default chain's result,
every counted penetrating limb vertex (ACCEPTANCE.md) of every frame by (its part, upper arm / forearm / hand or
leg, the parts the judge tests it against that hold it), as a share of all vertices over all frames (these add up to
pen %v), and the share of them deeper than 1 cm.

    PYTHONPATH=. flock /tmp/heavy.lock .venv/bin/python benchmarks/diag/pen_parts.py \\
        ../shared/data/motions/cmu/002_08.bvh ~/.cache/retarget/heldout/heldout_short-*.glb --frames 300

The clip is sent as a GLB on the average body and resampled to 30 fps, as the held-out evaluation does. Each
penetrating vertex's holding parts are read by winding numbers (slow: minutes for 300 frames).
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from retarget_core.motion import Motion
from retarget_core.pipeline import refine

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, write_json  # noqa: E402
from benchmarks.diag.deep_parts import DEEP_M, posed_case  # noqa: E402


def by_part(case: Any, motion: Motion) -> dict[str, dict[str, float]]:
    """``{"part / segment / in parts": {"pen_percent", "deeper_1cm_percent"}}`` of ``motion`` on the case's target."""
    pc = posed_case(case, motion)
    counts: collections.Counter[str] = collections.Counter()
    deep: collections.Counter[str] = collections.Counter()
    for f, p, depth in pc.limb_depths():
        for v in np.nonzero(depth > 0)[0]:
            key, _ = pc.label(f, p, int(v))
            counts[key] += 1
            deep[key] += int(depth[v] > DEEP_M)
    total = 100.0 / (len(pc.posed) * pc.character.num_vertices)
    return {k: {"pen_percent": round(n * total, 4), "deeper_1cm_percent": round(deep[k] * total, 4)}
            for k, n in counts.most_common()}  # fmt: skip


def main() -> None:
    a = case_parser(__doc__, frames=300).parse_args()
    torch.set_num_threads(2)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    out: dict[str, Any] = {"clip": a.clip.stem, "body": Path(a.body).stem}
    for label, motion in (("copy", case.prepared.before), ("full", refine(case.prepared).after)):
        out[label] = by_part(case, motion)
        print(f"{label}: pen %v {sum(r['pen_percent'] for r in out[label].values()):.4f}")
        for key, row in out[label].items():
            print(f"  {row['pen_percent']:.4f} %v (deeper than 1 cm {row['deeper_1cm_percent']:.4f})  {key}")
    if a.json:
        write_json(a.json, out)


if __name__ == "__main__":
    main()
