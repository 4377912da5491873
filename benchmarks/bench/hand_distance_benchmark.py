"""Time the exact hand-to-part distances (``contacts/hand_distance.py``) and compare two versions of them.

Cases: every 5th shared CMU clip and the hard clips (``motions/cmu_hard``, where fetched), each on one of the bulky
sample, the Quaternius Witch and the cryptovoxels VRM (in turn; the rigs where fetched, see
retarget_core/data/samples/rigs/README.md), each clip's first 300 source frames resampled to 30 fps: the source on
its body (what contact detection measures) and "before" on the target (what the metrics measure). Prints and
writes the seconds per case.

    PYTHONPATH=. python benchmarks/bench/hand_distance_benchmark.py [-o out.json] [--save DIR] [--compare DIR]

``--save DIR`` keeps each case's posed frames and results; ``--compare DIR`` measures the frames saved there
(by another version of the code, e.g. from a git worktree) and counts the (frame, hand, part) groups whose
distance, inside flag or closest pairs differ.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import add_output, machine, parser, results_dir, shared_data, timer, write_json  # noqa: E402

TARGETS = ("characters/mh_male_bulky.glb", "rigs/quaternius_witch.gltf", "rigs/cryptovoxels.vrm")


def cases(data: Path) -> list[tuple[Path, Path]]:
    """(clip, target) pairs: every 5th CMU clip and the hard clips, the targets in turn (those present)."""
    clips = sorted((data / "motions" / "cmu").glob("*.bvh"))[::5] + sorted((data / "motions" / "cmu_hard").glob("*"))
    targets = [data / t for t in TARGETS if (data / t).exists()]
    return [(clip, targets[i % len(targets)]) for i, clip in enumerate(clips)]


def posed_case(clip: Path, target: Path) -> dict[str, tuple[Any, ...]]:
    """Per side ("source", "before"): (parts, posed (F, V, 3), height, rest vertices)."""
    from retarget_core.body_parts import body_parts
    from retarget_core.jobs import JobInputs
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import prepare

    p = prepare(JobInputs(clip, target, options=RetargetOptions(fps=30.0, frame_end=300)))
    out = {}
    for side, ch, mapping, motion in (("source", p.source_body.character, p.source_body.mapping, p.source_view),
                                      ("before", p.target.character, p.target.mapping, p.before)):  # fmt: skip
        grot, gpos = motion.global_transforms()
        with torch.no_grad():
            out[side] = (body_parts(ch, mapping), ch.pose_vertices(grot, gpos), ch.height, ch.vertices)
    return out


def measured(parts: Any, posed: torch.Tensor, height: float, rest: torch.Tensor) -> tuple[Any, float]:
    """The distances of one side and the seconds they took (the body's geometry built outside the clock)."""
    from retarget_core.contacts.hand_distance import hand_part_distances, hand_part_geometry

    geom = hand_part_geometry(parts, rest, height)
    with timer() as t:
        found = hand_part_distances(None, parts, posed, geometry=geom, height=height)
    return found, t.wall_s


def differences(old: Any, new: Any) -> dict[str, int]:
    """Groups whose distance (beyond 1e-9 m), inside flag or closest pairs differ between two results."""
    both = torch.isfinite(old.distance) & torch.isfinite(new.distance)
    dist = (torch.isfinite(old.distance) != torch.isfinite(new.distance)) | (both & ((old.distance - new.distance).abs() > 1e-9))
    return {"groups_within_cutoff": int(torch.isfinite(new.distance).sum()), "distance_differs": int(dist.sum()),
            "inside_differs": int((old.inside != new.inside).sum()),
            "pairs_differ": int((old.pairs != new.pairs).flatten(3).any(-1).sum())}  # fmt: skip


def main() -> None:
    ap = parser(__doc__)
    add_output(ap, results_dir("bench") / "hand_distance_benchmark.json")
    ap.add_argument("--save", type=Path, help="keep each case's posed frames and results here")
    ap.add_argument("--compare", type=Path, help="measure the frames saved here and compare with their results")
    args = ap.parse_args()
    rows, total = [], 0.0
    for clip, target in cases(shared_data()):
        saved = args.compare / f"{clip.stem}.pt" if args.compare else None
        sides = torch.load(saved, weights_only=False) if saved else posed_case(clip, target)
        row: dict[str, Any] = {"clip": clip.name, "target": target.name}
        keep = {}
        for side, value in sides.items():
            parts, posed, height, rest = value[:4]
            found, seconds = measured(parts, posed, height, rest)
            total += seconds
            row[side] = {"frames": int(posed.shape[0]), "seconds": round(seconds, 3)}
            if saved:
                row[side].update(differences(value[4], found))
            keep[side] = (parts, posed, height, rest, found)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            torch.save(keep, args.save / f"{clip.stem}.pt")
        print(row, flush=True)
        rows.append(row)
    print(f"hand-to-part distances: {total:.2f} s over {len(rows)} cases", flush=True)
    write_json(args.output, {"machine": machine(), "seconds": round(total, 2), "cases": rows})


if __name__ == "__main__":
    main()
