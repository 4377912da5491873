"""Would turning the clavicles take the upper arms out of a bulky chest? One clip x body through the default chain,
then both clavicles (the canonical Shoulder joints) turned on every frame by a fixed angle, up or down about the
axis across the clavicle ("elev") or forward or back about the vertical ("prot"), each arm solved back onto its
wrist by two-bone IK (:func:`retarget_core.refine.hand_contacts.apply_moves`: the elbow keeps its side); the
judge's figures printed for the chain's result and for each turn.

    PYTHONPATH=. flock /tmp/heavy.lock .venv/bin/python benchmarks/diag/shrug_probe.py \\
        ../shared/data/motions/cmu/005_18.bvh ~/.cache/retarget/heldout/heldout_bulky-*.glb --frames 300

The clip is sent as a GLB on the average body and resampled to 30 fps, as the held-out evaluation does.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

from retarget_core import rotations as rot
from retarget_core.metrics.acceptance import figures_from_measures, measure_acceptance
from retarget_core.motion import Motion
from retarget_core.pipeline import refine
from retarget_core.refine.arms import Arm, about_axis, arms_of
from retarget_core.refine.hand_contacts import apply_moves

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, write_json  # noqa: E402

TURNS_DEG = (-10.0, -5.0, 5.0, 10.0)


def shrugged(motion: Motion, arms: list[Arm], kind: str, degrees: float) -> Motion:
    """``motion`` with each arm's clavicle turned by ``degrees`` ("elev": about the axis across the clavicle,
    positive up on both sides; "prot": about the vertical), the wrist then put back by two-bone IK."""
    sk = motion.skeleton
    grot, gpos = motion.global_transforms()
    local = motion.rotations.clone()
    for arm in arms:
        clavicle = sk.parents[arm.upper]
        bone = gpos[:, arm.upper] - gpos[:, clavicle]  # (F, 3)
        up = torch.tensor([0.0, 1.0, 0.0], dtype=bone.dtype).expand_as(bone)
        axis = torch.linalg.cross(bone, up) if kind == "elev" else up.clone()
        axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        side = 1.0 if arm.side == 0 else -1.0
        q = about_axis(axis, torch.full((len(bone),), side * math.radians(degrees), dtype=bone.dtype)).to(grot.dtype)
        local[:, clavicle] = rot.normalize(
            rot.mul(rot.inv(grot[:, sk.parents[clavicle]]), rot.mul(q, grot[:, clavicle]))
        )
    turned = Motion(sk, motion.fps, local, motion.translations.clone(), motion.name)
    _, moved = turned.global_transforms()
    back = torch.zeros(motion.num_frames, 2, 3)
    for arm in arms:
        back[:, arm.side] = (gpos[:, arm.hand] - moved[:, arm.hand]).float()
    return apply_moves(turned, arms, back, 0.995)


def main() -> None:
    ap = case_parser(__doc__, frames=300)
    a = ap.parse_args()
    torch.set_num_threads(1)
    case = prepare_case(a.clip, a.body, a.frames, a.source_body)
    target = case.prepared.target
    result = refine(case.prepared).after
    arms = arms_of(target.mapping, target.character.skeleton.parents)
    rows = []
    for kind, degrees in [("none", 0.0)] + [(k, d) for k in ("elev", "prot") for d in TURNS_DEG]:
        moved = result if kind == "none" else shrugged(result, arms, kind, degrees)
        f = figures_from_measures(measure_acceptance(target.character, target.mapping, moved), case.source)
        row = {"turn": kind, "degrees": degrees, "pen_percent": round(f.pen_percent, 4),
               "frames_over_1cm_percent": round(f.frames_over_1cm_percent, 2),
               "end_effector_error_cm": round(f.end_effector_error_cm, 3),
               "contact_preservation": f.contact_preservation}  # fmt: skip
        rows.append(row)
        print(row, flush=True)
    if a.json:
        write_json(a.json, {"clip": a.clip.stem, "body": Path(a.body).stem, "rows": rows})


if __name__ == "__main__":
    main()
