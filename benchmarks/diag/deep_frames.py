"""What the frames deeper than 1 cm are made of: for one clip x body through the default chain, every frame whose
deepest counted vertex (ACCEPTANCE.md) is over 1 cm, with that vertex's part, how deep the same vertex is in the
character's own rest pose (a body whose thighs or arms already overlap at rest), how much of its skin weight is on
joints of another part (a skinning fold: the vertex is dragged by both sides of a joint), and its distance along the
rest surface to the nearest part boundary.

    PYTHONPATH=. flock /tmp/heavy.lock .venv/bin/python benchmarks/diag/deep_frames.py \\
        ../shared/data/motions/cmu/005_18.bvh ~/.cache/retarget/heldout/heldout_heavy-*.glb --json out.json

The clip is sent as a GLB on the average body and resampled to 30 fps, as the held-out evaluation does.
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from retarget_core.metrics.acceptance import measure_pose
from retarget_core.metrics.acceptance_body import PARTS, acceptance_body
from retarget_core.pipeline import refine

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, write_json  # noqa: E402

DEEP_M = 0.01  # at 1.80 m


def foreign_weight(character: Any, part_of_joint: np.ndarray, part_of_vertex: np.ndarray) -> np.ndarray:
    """``(V,)`` share of each vertex's skin weight on joints whose part is not the vertex's own part."""
    joints = character.skin_joints.numpy()
    weights = character.skin_weights.clamp_min(0).numpy()
    other = part_of_joint[joints] != part_of_vertex[:, None]
    return (weights * other).sum(1) / np.maximum(weights.sum(1), 1e-12)


def joint_parts(body: Any, character: Any) -> np.ndarray:
    """``(J,)`` the part each joint's dominant vertices belong to (-1 for joints that dominate no vertex)."""
    joints, weights = character.skin_joints.numpy(), character.skin_weights.numpy()
    dominant = joints[np.arange(len(joints)), weights.argmax(1)]
    out = np.full(character.skeleton.num_joints, -1)
    for j in range(character.skeleton.num_joints):
        mine = body.part_of_vertex[dominant == j]
        if len(mine):
            out[j] = np.bincount(mine).argmax()
    return out


def classify(case: Any, motion: Any) -> dict[str, Any]:
    """Per deep frame: the deepest vertex's part, depth, rest depth, foreign weight and seam distance (cm)."""
    target = case.prepared.target
    character, mapping = target.character, target.mapping
    body = acceptance_body(character, mapping)
    k = body.scale_to_180
    rest = measure_pose(character, mapping, character.vertices.double().numpy()).depth * k
    foreign = foreign_weight(character, joint_parts(body, character), body.part_of_vertex)
    grot, gpos = motion.global_transforms()
    posed = character.pose_vertex_subset(torch.arange(character.num_vertices), grot, gpos).numpy()
    rows, kinds = [], collections.Counter()
    for f, p in enumerate(posed):
        depth = measure_pose(character, mapping, p).depth * k
        limb = body.part_of_vertex != PARTS.index("head")
        v = int(np.argmax(np.where(limb, depth, 0)))
        if depth[v] <= DEEP_M:
            continue
        kind = "rest overlap" if rest[v] > 0.5 * depth[v] else "fold" if foreign[v] > 0.2 else "pose"
        kinds[kind] += 1
        rows.append({"frame": f, "part": PARTS[body.part_of_vertex[v]], "depth_cm": round(100 * depth[v], 2),
                     "rest_depth_cm": round(100 * rest[v], 2), "foreign_weight": round(float(foreign[v]), 2),
                     "seam_cm": round(100 * float(body.seam_distance[v]) * k, 1), "kind": kind})  # fmt: skip
    return {"frames": len(posed), "deep": len(rows), "kinds": dict(kinds), "rows": rows}


def main() -> None:
    a = case_parser(__doc__).parse_args()
    torch.set_num_threads(1)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    result = refine(case.prepared)
    out = {"clip": a.clip.stem, "body": Path(a.body).stem,
           "copy": classify(case, case.prepared.before), "full": classify(case, result.after)}  # fmt: skip
    for name in ("copy", "full"):
        r = out[name]
        print(f"{name}: {r['deep']} of {r['frames']} frames deeper than 1 cm; {r['kinds']}")
        for row in r["rows"][:: max(1, len(r["rows"]) // 8)]:
            print("   ", row)
    if a.json:
        write_json(a.json, out)


if __name__ == "__main__":
    main()
