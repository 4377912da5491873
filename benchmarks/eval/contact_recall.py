"""Hand self-contact recall and false contacts on the shared clips, and the time detection takes.

For every clip (CMU BVH, resampled to 30 fps, on the built-in body sized to its skeleton, as the pipeline does
for a bare BVH), per frame:

- reference: a hand is within 1.5 cm (at 1.80 m) of another part's surface, or inside it (ACCEPTANCE.md "Hand
  self-contact"; the hand's own arm excluded), by :func:`retarget_core.contacts.hand_distance.hand_part_distances`;
- far: both hands are more than 3 cm from every other part;
- detected: :func:`retarget_core.contacts.self_contact.detect_self_contacts` finds a contact.

Recall = detected reference frames / reference frames; false-contact frames = detected far frames. A clip "has
hand contacts" when it has at least ``--min-contact-frames`` reference frames. Also: the distance of the nearest
hand on reference frames (how much of "touching" is sunk into the body), and the time per frame of the distance
queries and of the whole detection (single torch thread, wall and CPU).

    flock /tmp/heavy.lock python benchmarks/eval/contact_recall.py [--clips 002_07 007_01] [--max-frames 300]
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import torch

from retarget_core.body_parts import CLUSTERS, body_parts
from retarget_core.contacts.hand_distance import HandDistanceParams, hand_part_distances, hand_part_geometry
from retarget_core.contacts.self_contact import SelfContactParams, contacts_from_distances

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import (  # noqa: E402
    SHARED_DATA,
    add_output,
    load_clip,
    parser,
    results_dir,
    source_view,
    timer,
    write_json,
)

REFERENCE_M = 0.015  # ACCEPTANCE.md: a source contact is a hand within 1.5 cm of a part
FAR_M = 0.03  # the "hands more than 3 cm from everything"
BANDS_M = (0.0, 0.005, 0.01, 0.015)  # histogram of the nearest hand's distance on reference frames


def clip_paths(names: list[str] | None) -> list[Path]:
    motions = SHARED_DATA / "motions"
    paths = sorted((motions / "cmu").glob("*.bvh")) + sorted((motions / "cmu_mb").glob("*.bvh"))
    if names:
        paths = [p for p in paths if p.stem in names or f"{p.parent.name}/{p.stem}" in names]
    return paths


def measure_clip(path: Path, max_frames: int | None, fps: float) -> dict[str, Any]:
    body, mapping, view = source_view(load_clip(path, fps, max_frames))
    parts = body_parts(body, mapping)
    grot, gpos = view.global_transforms()
    with torch.no_grad():
        posed = body.pose_vertices(grot, gpos)
    params = SelfContactParams()
    dparams = HandDistanceParams(pairs=params.pairs)
    with timer() as whole:
        with timer() as distances:
            geom = hand_part_geometry(parts, body.vertices, body.height, dparams)
            dist = hand_part_distances(body, parts, posed, dparams, geom)
        contacts = contacts_from_distances(parts, posed, dist, body.height, view.fps, params)
    wall_d, wall_all, cpu_all = distances.wall_s, whole.wall_s, whole.cpu_s
    s = body.height / 1.80
    d = torch.where(dist.measured[None], dist.distance, torch.inf)  # (F, 2, P)
    nearest = d.amin((1, 2))
    reference = nearest <= REFERENCE_M * s
    far = nearest > FAR_M * s
    detected = contacts.frames_with_contact()
    f_n = int(posed.shape[0])
    bands = {}
    for lo, hi in zip(BANDS_M, BANDS_M[1:] + (REFERENCE_M,), strict=True):
        if lo == 0.0:
            bands["inside"] = int((reference & (nearest == 0)).sum())
            bands[f"0-{hi * 100:g} cm"] = int((reference & (nearest > 0) & (nearest <= hi * s)).sum())
        elif hi > lo:
            bands[f"{lo * 100:g}-{hi * 100:g} cm"] = int((reference & (nearest > lo * s) & (nearest <= hi * s)).sum())
    pair_frames = {}
    for h, hand in enumerate(dist.hands):
        for c, part in enumerate(CLUSTERS):
            n = int((d[:, h, c] <= REFERENCE_M * s).sum())
            if n:
                pair_frames[f"{hand}-{part}"] = n
    n_ref = int(reference.sum())
    return {
        "clip": path.stem if path.parent.name == "cmu" else f"{path.parent.name}/{path.stem}",
        "frames": f_n,
        "fps": view.fps,
        "body_height_m": round(body.height, 3),
        "reference_frames": n_ref,
        "detected_frames": int(detected.sum()),
        "detected_reference_frames": int((detected & reference).sum()),
        "recall": round(int((detected & reference).sum()) / n_ref, 4) if n_ref else None,
        "far_frames": int(far.sum()),
        "false_contact_frames": int((detected & far).sum()),
        "contacts": contacts.count,
        "touching_pairs_frames": pair_frames,
        "nearest_on_reference_frames": bands,
        "ms_per_frame_distances": round(wall_d / max(f_n, 1) * 1e3, 3),
        "ms_per_frame_detection": round(wall_all / max(f_n, 1) * 1e3, 3),
        "cpu_ms_per_frame_detection": round(cpu_all / max(f_n, 1) * 1e3, 3),
    }


def write_markdown(result: dict[str, Any], path: Path) -> None:
    rows = result["clips"]
    lines = [
        "# Hand self-contact recall on the shared clips",
        "",
        f"Made by `benchmarks/eval/contact_recall.py` ({result['when']}, {result['machine']}). Reference frames: a hand "
        "within 1.5 cm (at 1.80 m) of another part or inside it; far frames: both hands more than 3 cm from every "
        f"other part. Clips with at least {result['min_contact_frames']} reference frames count as clips with hand "
        "contacts.",
        "",
        f"**Clips with hand contacts: {result['summary']['contact_clips']} of {len(rows)}.** Over them: recall "
        f"{result['summary']['recall']}, false-contact frames {result['summary']['false_contact_frames']} of "
        f"{result['summary']['far_frames']} far frames; lowest clip recall {result['summary']['min_recall']}. "
        f"Detection {result['summary']['ms_per_frame_detection']} ms per frame (wall, mean over all clips; "
        f"distances {result['summary']['ms_per_frame_distances']} ms).",
        "",
        "| clip | frames | reference | detected | recall | far | false | inside | 0-0.5 cm | 0.5-1 cm | 1-1.5 cm | "
        "touching (hand-part: frames) | ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if not r["has_contacts"]:
            continue
        b = r["nearest_on_reference_frames"]
        top = sorted(r["touching_pairs_frames"].items(), key=lambda kv: -kv[1])[:3]
        lines.append(
            f"| {r['clip']} | {r['frames']} | {r['reference_frames']} | {r['detected_reference_frames']} | "
            f"{r['recall']} | {r['far_frames']} | {r['false_contact_frames']} | {b.get('inside', 0)} | "
            f"{b.get('0-0.5 cm', 0)} | {b.get('0.5-1 cm', 0)} | {b.get('1-1.5 cm', 0)} | "
            + ", ".join(f"{k}: {v}" for k, v in top)
            + f" | {r['ms_per_frame_detection']} |"
        )
    others = [r for r in rows if not r["has_contacts"]]
    lines += [
        "",
        f"Clips without hand contacts ({len(others)}): "
        + ", ".join(f"{r['clip']} ({r['reference_frames']} ref., {r['false_contact_frames']} false)" for r in others),
        "",
    ]
    path.write_text("\n".join(lines))


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--clips", nargs="*", help="clip names (e.g. 002_07); default: every shared clip")
    ap.add_argument("--max-frames", type=int, default=300, help="frames per clip at 30 fps (0: all)")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--min-contact-frames", type=int, default=15, help="reference frames for a clip to count")
    add_output(ap, results_dir("eval") / "contact_recall.json", "the result JSON; the table beside it as .md")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for path in clip_paths(args.clips):
        r = measure_clip(path, args.max_frames or None, args.fps)
        r["has_contacts"] = r["reference_frames"] >= args.min_contact_frames
        rows.append(r)
        print(
            f"{r['clip']:>10} frames {r['frames']:5d} ref {r['reference_frames']:5d} det {r['detected_reference_frames']:5d} "
            f"recall {r['recall']} far {r['far_frames']:5d} false {r['false_contact_frames']:4d} "
            f"{r['ms_per_frame_detection']:.2f} ms/frame {dict(sorted(r['touching_pairs_frames'].items()))}",
            flush=True,
        )
    with_c = [r for r in rows if r["has_contacts"]]
    ref = sum(r["reference_frames"] for r in with_c)
    det = sum(r["detected_reference_frames"] for r in with_c)
    frames = sum(r["frames"] for r in rows)
    summary = {
        "contact_clips": len(with_c),
        "contact_clip_names": [r["clip"] for r in with_c],
        "recall": round(det / ref, 4) if ref else None,
        "min_recall": min((r["recall"] for r in with_c), default=None),
        "far_frames": sum(r["far_frames"] for r in with_c),
        "false_contact_frames": sum(r["false_contact_frames"] for r in with_c),
        "false_contact_frames_all_clips": sum(r["false_contact_frames"] for r in rows),
        "ms_per_frame_detection": round(sum(r["ms_per_frame_detection"] * r["frames"] for r in rows) / max(frames, 1), 3),
        "ms_per_frame_distances": round(sum(r["ms_per_frame_distances"] * r["frames"] for r in rows) / max(frames, 1), 3),
    }
    result = {
        "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs (shared), torch threads 1",
        "fps": args.fps,
        "max_frames": args.max_frames,
        "min_contact_frames": args.min_contact_frames,
        "thresholds": {k: v for k, v in SelfContactParams().__dict__.items()},
        "summary": summary,
        "clips": rows,
    }
    write_json(args.output, result)
    write_markdown(result, args.output.with_suffix(".md"))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
