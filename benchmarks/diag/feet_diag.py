"""Why a result's feet read planted or not: per frame, for the source (a GLB on the average body, as the
held-out evaluation sends it) and for the copy baseline ("before") on a body, the judge's inputs to the foot
label (ACCEPTANCE.md): the toe joint's (the ankle's on a rig without toes) height above its rest height and the lowest foot vertex, in cm at a
1.80 m character, and the labels themselves.

    PYTHONPATH=. python benchmarks/diag/feet_diag.py \\
        ../shared/data/motions/cmu/002_05.bvh ~/.cache/retarget/heldout/heldout_heavy-cdfa1e99e730.glb

``--frames`` (default 100) caps the clip; ``--json`` writes the series.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.metrics.acceptance import CANONICAL_JOINTS, ClipAcceptance, measure_acceptance
from retarget_core.metrics.feet_acceptance import REFERENCE_HEIGHT_M, SIDES

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import case_parser, prepare_case, write_json  # noqa: E402


def toe_joints(mapping: JointMapping) -> list[str]:
    """The canonical joint the judge reads as each side's toe: ToeBase, or the ankle on rigs without toes."""
    return [f"{s}ToeBase" if f"{s}ToeBase" in mapping.joints else f"{s}Foot" for s in SIDES]


def rest_toe_heights(character: Character, mapping: JointMapping) -> list[float]:
    """Rest height (m at 1.80 m) of the left and right toe joints (:func:`toe_joints`)."""
    _, rest = character.skeleton.rest_global()
    k = REFERENCE_HEIGHT_M / character.height
    return [float(rest[mapping.joints[name], 1]) * k for name in toe_joints(mapping)]


def series(measured: ClipAcceptance, mapping: JointMapping, rest_toe: list[float]) -> dict[str, list[list[float]]]:
    """Per side: toe height above rest (cm), lowest foot vertex (cm), planted (0/1), each ``(F,)``."""
    out: dict[str, list[list[float]]] = {"toe_above_rest_cm": [], "lowest_foot_cm": [], "planted": []}
    for s, name in enumerate(toe_joints(mapping)):
        toe = CANONICAL_JOINTS.index(name)
        out["toe_above_rest_cm"].append(np.round((measured.joints[:, toe, 1] - rest_toe[s]) * 100, 2).tolist())
        out["lowest_foot_cm"].append(np.round(measured.lowest_foot[:, s] * 100, 2).tolist())
        out["planted"].append(measured.planted[:, s].astype(int).tolist())
    return out


def main() -> None:
    args = case_parser(__doc__).parse_args()
    case = prepare_case(args.clip, args.body, args.frames, args.source_body, method="copy")
    prepared, tgt = case.prepared, case.prepared.target
    rows = {
        "source": series(case.source, case.source_mapping, rest_toe_heights(case.source_character, case.source_mapping)),
        "before": series(measure_acceptance(tgt.character, tgt.mapping, prepared.before), tgt.mapping,
                         rest_toe_heights(tgt.character, tgt.mapping)),  # fmt: skip
    }
    np.set_printoptions(linewidth=200, precision=1, suppress=True)
    for s, side in enumerate(SIDES):
        print(side)
        for who, r in rows.items():
            for key in ("toe_above_rest_cm", "lowest_foot_cm", "planted"):
                print(f"  {who:6} {key:18}", np.array(r[key][s]))
    agree = np.array(rows["source"]["planted"]) == np.array(rows["before"]["planted"])
    print(f"foot accuracy of the copy: {agree.mean():.3f}")
    if args.json:
        write_json(args.json, {"clip": args.clip.stem, "body": str(args.body), **rows})


if __name__ == "__main__":
    main()
