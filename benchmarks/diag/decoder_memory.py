"""How long the recurrent decoder remembers ESO's offsets: the warm-up of the windowed decode
(`retarget_core/model/windowed_decode.py`) rests on this.

Runs one job's ESO (the default chain up to ESO on a clip and body), takes the offsets it found, and for a few cut
frames ``a`` decodes the clip with the offsets kept only before ``a``: the largest change of the decoder's output
(rot6 residuals, all joints) against the plain decode, at ``a - 1`` (where they act) and ``k`` frames after
``a``. Then the windowed decode with several warm-ups against the whole-clip decode, on the same offsets.

    PYTHONPATH=. .venv/bin/python benchmarks/diag/decoder_memory.py [--motion CLIP] [--target BODY] [-o out.json]
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
import retarget_core.model.eso as eso  # noqa: E402
from benchmarks.common import BULKY_SAMPLE, add_clip_options, add_output, parser, results_dir, run_job_once, write_json  # noqa: E402
from retarget_core.model.windowed_decode import WINDOW_FRAMES, decode_windows, plan_windows  # noqa: E402

AFTER = (0, 5, 10, 15, 20, 30, 40)
WARM_UPS = (0, 5, 10, 20, 30)


def _memory(pb: Any, dh: torch.Tensor) -> dict[str, Any]:
    """The figures above for one solved problem ``pb`` and its knot offsets ``dh (1, K, H)``."""
    with torch.no_grad():
        offset = torch.einsum("tk,bkh->bth", pb.interp, dh) * pb.weight[None, : pb.last, None]
        states = pb.states[:, : pb.last]
        plain, _ = pb.model.decode(states, pb.embedding)
        whole, _ = pb.model.decode(states + offset, pb.embedding)
        cuts = {}
        for a in range(int(pb.windows.first) + 40, pb.last - max(AFTER) - 1, 50):
            cut = offset.clone()
            cut[:, a:] = 0
            moved = (pb.model.decode(states + cut, pb.embedding)[0] - plain).abs().amax(dim=(0, 2, 3))
            cuts[a] = {"at_cut": float(moved[a - 1]), **{f"+{k}": float(moved[a + k]) for k in AFTER}}
        windowed = {}
        for w in WARM_UPS:
            win = plan_windows(pb.model, states, pb.embedding, int(pb.windows.first), WINDOW_FRAMES, w)
            rot6, _ = decode_windows(pb.model, win, states + offset, pb.embedding)
            windowed[w] = float((rot6 - whole[:, win.first :]).abs().max())
    return {"offset_effect_after_cut": cuts, "windowed_vs_whole_max": windowed,
            "largest_output_change": float((whole - plain).abs().max())}  # fmt: skip


def main() -> None:
    ap = parser(__doc__)
    add_clip_options(ap)
    ap.add_argument("--target", default=str(BULKY_SAMPLE), help="the target body (GLB, or builtin:<preset>)")
    add_output(ap, results_dir("diag") / "decoder_memory.json")
    args = ap.parse_args()
    found: dict[str, Any] = {}
    solve = eso._solve

    def solve_and_measure(pb: Any, p: Any) -> torch.Tensor:
        dh = solve(pb, p)
        found.update(_memory(pb, dh))
        return dh

    eso._solve = solve_and_measure
    run_job_once(args.motion, args.target, args.frames, args.fps, None, {"collisions": False, "foot_lock": False})
    for a, row in found.get("offset_effect_after_cut", {}).items():
        print(f"cut at {a}: " + ", ".join(f"{k} {v:.2e}" for k, v in row.items()))
    print("windowed decode vs whole clip, by warm-up:", {k: f"{v:.1e}" for k, v in found.get("windowed_vs_whole_max", {}).items()})
    write_json(args.output, {"motion": args.motion.name, "target": Path(args.target).name, "frames": args.frames, **found})


if __name__ == "__main__":
    main()
