"""The source figures of metrics/source.py on the shared clips, to choose the warning thresholds.

Every clip (resampled to 30 fps, first 300 frames) on the body the pipeline would give it (the built-in body
sized to its skeleton), measured with :func:`retarget_core.metrics.source.measure_source`; plus the same clips
with joint jitter added (Gaussian noise on the root position and small rotation noise on every joint) to see
where jitter starts. Prints a table and writes benchmarks/diag/results/source_calibration.json.

    flock /tmp/heavy.lock python benchmarks/diag/source_calibration.py [--clips 007_01 002_05 ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import torch

from retarget_core import rotations
from retarget_core.body_cache import part_sdf_for
from retarget_core.contacts.foot_contact import detect_foot_contacts
from retarget_core.copy_retarget import copy_retarget
from retarget_core.metrics.report import SourceMetrics
from retarget_core.metrics.source import measure_source
from retarget_core.motion import Motion

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    JUDGE_FPS,
    SHARED_DATA,
    add_output,
    load_clip,
    parser,
    results_dir,
    source_view,
    timer,
    write_json,
)

FIGURES = ("hand_inside_frames_percent", "hand_depth_max", "foot_skate", "foot_slide", "foot_slide_frames_percent",
           "ground_below_frames_percent", "ground_penetration_mean", "foot_float_mean", "jerk", "jerk_to_acceleration")  # fmt: skip


def jittered(motion: Motion, position_m: float, angle_deg: float, seed: int = 0) -> Motion:
    """``motion`` with Gaussian noise: ``position_m`` on the root translation, ``angle_deg`` on every rotation."""
    g = torch.Generator().manual_seed(seed)
    trans = motion.translations.clone()
    trans[:, 0] += torch.randn(trans[:, 0].shape, generator=g) * position_m
    axis = torch.randn(motion.rotations.shape[:-1] + (3,), generator=g) * (angle_deg * torch.pi / 180.0)
    import roma

    noise = roma.rotvec_to_unitquat(axis)
    return Motion(motion.skeleton, motion.fps, rotations.mul(motion.rotations, noise), trans, motion.name + "+jitter")


def figures(metrics: SourceMetrics) -> dict[str, Any]:
    out = {}
    for name in FIGURES:
        v = getattr(metrics, name)
        out[name] = v.value_at_180 if hasattr(v, "value_at_180") else v
    out["flags"] = [f.name for f in metrics.flags]
    return out


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--clips", nargs="*", default=None, help="clip names (default: every shared CMU clip)")
    ap.add_argument("--frames", type=int, default=300, help="first frames at 30 fps")
    add_output(ap, results_dir("diag") / "source_calibration.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    paths = sorted((SHARED_DATA / "motions" / "cmu").glob("*.bvh"))
    if args.clips:
        paths = [p for p in paths if p.stem in args.clips]
    rows = []
    with timer() as took:
        for path in paths:
            loaded = load_clip(path, JUDGE_FPS, args.frames)
            body, body_map, clean = source_view(loaded)
            _, sdf = part_sdf_for(body, body_map)
            jitter = copy_retarget(jittered(loaded.motion, 0.001, 0.3), loaded.mapping, body.skeleton, body_map)
            for variant, view in (("clean", clean), ("jitter 1 mm / 0.3 deg", jitter)):
                _, gpos = view.global_transforms()
                feet = detect_foot_contacts(gpos, body.skeleton.rest_global()[1], body_map, body.height, view.fps)
                metrics, _ = measure_source(body, body_map, view, sdf, feet)
                rows.append({"clip": path.stem, "variant": variant, **figures(metrics)})
                print(json.dumps(rows[-1]), flush=True)
    write_json(args.output, {"seconds": round(took.wall_s, 1), "rows": rows})


if __name__ == "__main__":
    main()
