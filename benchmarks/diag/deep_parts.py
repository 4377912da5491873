"""What the frames deeper than 1 cm are, part against part: for one clip x body through the default chain, every
frame whose deepest counted limb vertex (ACCEPTANCE.md) is over 1 cm, with that vertex's part, where it lies along
its arm (0 the shoulder joint, 1 the elbow, 2 the wrist, beyond 2 the hand) and which parts the judge tests it
against it lies inside. Counts per (part, segment, parts inside) and the quartiles of the position along the arm.

    PYTHONPATH=. flock /tmp/heavy.lock .venv/bin/python benchmarks/diag/deep_parts.py \\
        ../shared/data/motions/cmu/005_02.bvh ~/.cache/retarget/heldout/heldout_heavy-*.glb --frames 300

The clip is sent as a GLB on the average body and resampled to 30 fps, as the held-out evaluation does.
"""

from __future__ import annotations

import collections
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from retarget_core.metrics.acceptance import measure_pose
from retarget_core.metrics.acceptance_body import LIMB_TESTS, PARTS, AcceptanceBody, acceptance_body
from retarget_core.pipeline import refine
from retarget_core.refine.arms import Arm, arms_of

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, write_json  # noqa: E402

DEEP_M = 0.01  # at 1.80 m


def winding(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> float:
    """The winding number of the closed mesh ``vertices (V, 3)``, ``faces (T, 3)`` at ``point (3,)``."""
    a, b, c = (vertices[faces[:, i]] - point for i in range(3))
    la, lb, lc = (np.linalg.norm(u, axis=1) for u in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
    den = den + np.einsum("ij,ij->i", c, a) * lb
    return float(np.arctan2(num, den).sum() / (2 * np.pi))


def along_arm(arm: Arm, gpos: np.ndarray, x: np.ndarray) -> float:
    """Where ``x (3,)`` lies along ``arm`` on joint positions ``gpos (J, 3)``: 0 shoulder, 1 elbow, 2 wrist."""
    s, e, w = gpos[arm.upper], gpos[arm.fore], gpos[arm.hand]
    t = float(np.dot(x - s, e - s) / np.dot(e - s, e - s))
    return t if t < 1.0 else 1.0 + float(np.dot(x - e, w - e) / np.dot(w - e, w - e))


def inside_of(body: AcceptanceBody, part: str, posed: np.ndarray, x: np.ndarray) -> tuple[str, ...]:
    """The parts ``part`` is tested against whose closed mesh on ``posed (V, 3)`` holds ``x (3,)``."""
    out = []
    for other in LIMB_TESTS[part]:
        closed = body.part(other)
        if closed is not None and abs(winding(closed.posed(posed[None])[0], closed.faces, x)) > 0.5:
            out.append(other)
    return tuple(out)


@dataclass
class PosedCase:
    """A motion on a case's target: its judged body, arms by side, joint positions ``gpos (F, J, 3)`` and vertices
    ``posed (F, V, 3)``, and ``limb (V,)`` the vertices outside the head."""

    character: Any
    mapping: Any
    body: AcceptanceBody
    arms: dict[int, Arm]
    gpos: torch.Tensor
    posed: np.ndarray
    limb: np.ndarray

    def limb_depths(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """Per frame: its index, the posed vertices ``(V, 3)`` and the judge's limb depths ``(V,)`` at 1.80 m."""
        for f, p in enumerate(self.posed):
            depth = measure_pose(self.character, self.mapping, p).depth * self.body.scale_to_180
            yield f, p, np.where(self.limb, depth, 0.0)

    def label(self, f: int, p: np.ndarray, v: int) -> tuple[str, float | None]:
        """Vertex ``v`` of frame ``f`` (posed ``p``): "part / segment / in parts", and where along its arm it lies
        (0 shoulder, 1 elbow, 2 wrist; None off the arms)."""
        part = PARTS[self.body.part_of_vertex[v]]
        side = 0 if part.startswith("left") else 1
        segment, t = "leg", None
        if part.endswith("arm") and side in self.arms:
            t = along_arm(self.arms[side], self.gpos[f].numpy(), p[v])
            segment = "upper arm" if t < 1.0 else "forearm" if t < 2.0 else "hand"
        return f"{part} / {segment} / in {'+'.join(inside_of(self.body, part, p, p[v])) or 'none read'}", t


def posed_case(case: Any, motion: Any) -> PosedCase:
    """``motion`` posed on the case's target (:class:`PosedCase`)."""
    character, mapping = case.prepared.target.character, case.prepared.target.mapping
    body = acceptance_body(character, mapping)
    arms = {arm.side: arm for arm in arms_of(mapping, character.skeleton.parents)}
    grot, gpos = motion.global_transforms()
    posed = character.pose_vertex_subset(torch.arange(character.num_vertices), grot, gpos).numpy()
    return PosedCase(character, mapping, body, arms, gpos, posed, body.part_of_vertex != PARTS.index("head"))


def breakdown(case: Any, motion: Any) -> dict[str, Any]:
    """The deep frames of ``motion`` on the case's target, counted by (part, segment, parts inside)."""
    pc = posed_case(case, motion)
    counts: collections.Counter[str] = collections.Counter()
    along = []
    for f, p, depth in pc.limb_depths():
        v = int(np.argmax(depth))
        if depth[v] <= DEEP_M:
            continue
        key, t = pc.label(f, p, v)
        counts[key] += 1
        if t is not None:
            along.append(t)
    quart = np.percentile(along, [10, 25, 50, 75, 90]).round(2).tolist() if along else []
    return {"frames": len(pc.posed), "deep": sum(counts.values()), "counts": dict(counts.most_common()), "along_quantiles": quart}


def main() -> None:
    a = case_parser(__doc__, frames=300).parse_args()
    torch.set_num_threads(2)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    out = {"clip": a.clip.stem, "body": Path(a.body).stem, **breakdown(case, refine(case.prepared).after)}
    print(f"{out['clip']} x {out['body']}: {out['deep']} of {out['frames']} frames deeper than 1 cm")
    for key, n in out["counts"].items():
        print(f"  {n:4d}  {key}")
    print(f"  along the arm (0 shoulder, 1 elbow, 2 wrist), 10/25/50/75/90 %: {out['along_quantiles']}")
    if a.json:
        write_json(a.json, out)


if __name__ == "__main__":
    main()
