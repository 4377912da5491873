"""Time per frame of the network and of ESO on a 300-frame held-out clip on the 13k-vertex bulky body (one
torch thread, per-body cache warm). Writes benchmarks/bench/results/recurrent_speed.json. Run under the heavy lock:

    flock /tmp/heavy.lock python benchmarks/bench/recurrent_speed.py
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from retarget_core.cases import context_from_prepared, prepared_case
from retarget_core.refine import eso, recurrent

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"


def main() -> None:
    torch.set_num_threads(1)
    prep = prepared_case(DATA / "motions" / "cmu" / "005_10.bvh", DATA / "characters" / "mh_male_bulky.glb", 300)
    ctx = context_from_prepared(prep)
    recurrent.run(ctx, ctx.before)  # load the weights once
    out: dict[str, object] = {"clip": "005_10", "body": "mh_male_bulky", "frames": ctx.num_frames}
    t = time.perf_counter()
    net = recurrent.run(ctx, ctx.before)
    out["network_ms_per_frame"] = round(1000 * (time.perf_counter() - t) / ctx.num_frames, 3)
    for iterations in (30, 12):
        ctx.options = ctx.options.model_copy(update={"eso_iterations": iterations})
        t = time.perf_counter()
        rep = eso.run(ctx, net.motion).report
        out[f"eso_{iterations}_ms_per_frame"] = round(1000 * (time.perf_counter() - t) / ctx.num_frames, 3)
        out[f"eso_{iterations}_frames_optimised"] = rep.get("frames_optimised")
    path = REPO / "benchmarks" / "bench" / "results" / "recurrent_speed.json"
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
