"""Time per frame of the network and of ESO (30 and 12 iterations) on a 300-frame held-out clip on the 13k-vertex
bulky body (one torch thread, per-body cache warm). Writes benchmarks/bench/results/recurrent_speed.json. Run
under the heavy lock:

    flock /tmp/heavy.lock .venv/bin/python benchmarks/bench/recurrent_speed.py [--clip 005_10] [--frames 300]
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from retarget_core.cases import context_from_prepared, prepared_case
from retarget_core.refine import eso, recurrent

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    add_output,
    character_path,
    clip_path,
    machine,
    parser,
    results_dir,
    timer,
    write_json,
)

ESO_ITERATIONS = (30, 12)


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--clip", default="005_10", help="a shared CMU clip (one of the held-out clips)")
    ap.add_argument("--body", default="mh_male_bulky", help="a shared character")
    ap.add_argument("--frames", type=int, default=300)
    add_output(ap, results_dir("bench") / "recurrent_speed.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    ctx = context_from_prepared(prepared_case(clip_path(args.clip), character_path(args.body), args.frames))
    recurrent.run(ctx, ctx.before)  # load the weights once
    out: dict[str, object] = {"clip": args.clip, "body": args.body, "frames": ctx.num_frames}
    with timer() as took:
        net = recurrent.run(ctx, ctx.before)
    out["network_ms_per_frame"] = took.ms_per_frame(ctx.num_frames)
    for iterations in ESO_ITERATIONS:
        ctx.options = ctx.options.model_copy(update={"eso_iterations": iterations})
        with timer() as took:
            rep = eso.run(ctx, net.motion).report
        out[f"eso_{iterations}_ms_per_frame"] = took.ms_per_frame(ctx.num_frames)
        out[f"eso_{iterations}_frames_optimised"] = rep.get("frames_optimised")
    out["machine"] = machine()
    print({k: v for k, v in out.items() if k != "machine"})
    write_json(args.output, out)


if __name__ == "__main__":
    main()
