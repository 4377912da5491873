"""Render, x-ray and per body part, what the penetration measure counts at chosen frames (PNG).

A check a person can look at: the body drawn semi-transparent, every vertex the measure counts (deeper than the
3 mm tolerance, ``ClipMeasures.vertex_depth``) as a dot coloured by its part (head, torso, each arm, each leg),
a close-up of where most of them are, and two cross-sections through the deepest one (horizontal and along the
body's left-right axis) with each part's outline in its colour: a counted vertex lies inside the outline of
the part it entered. The title says, per (part, entered part), how many vertices and how deep, and how many
counted vertices lie within 3 cm along the rest surface of the part they enter (joint folds: armpit, crotch,
the neck's crease; the acceptance measure does not count those, so this number should be 0).

    python benchmarks/diag/render_penetration.py ../shared/data/motions/cmu/007_01.bvh \
        --body ../shared/data/characters/mh_male_bulky.glb --frames 40 120 -o benchmarks/diag/results
    python benchmarks/diag/render_penetration.py CLIP --body BODY --auto 3   # the 3 frames counting the most

Frames are of the clip resampled to 30 fps (as the evaluation does). Writes ``pen_<clip>_<body>_f<frame>.png``
and prints one JSON line per frame with the figures of the title.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from retarget_core import rotations  # noqa: E402
from retarget_core.body_cache import part_sdf_for  # noqa: E402
from retarget_core.body_parts import CLUSTERS, BodyParts  # noqa: E402
from retarget_core.canonical import JointMapping  # noqa: E402
from retarget_core.character import Character  # noqa: E402
from retarget_core.copy_retarget import copy_retarget  # noqa: E402
from retarget_core.energy.sdf import (  # noqa: E402
    PartSDF,
    SDFParams,
    build_part_sdf,
    effective_depth,
    geodesic_to_parts,
    sample_pairs,
    segment_matrices,
)
from retarget_core.loading import load_character  # noqa: E402
from retarget_core.metrics.compute import MetricParams, measure_clip  # noqa: E402
from retarget_core.motion import Motion  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import JUDGE_FPS, frame_3d, load_clip, parser, results_dir  # noqa: E402

PART_COLORS = {
    "head": "#9b59b6", "torso": "#e67e22", "left_arm": "#2e86de", "right_arm": "#00b8b8",
    "left_leg": "#27ae60", "right_leg": "#a3cb38",
}  # fmt: skip
FOLD_BAND_M = 0.03
"""At 1.80 m: a counted vertex this close (along the rest mesh) to the part it enters is in a joint fold; the
acceptance measure leaves such vertices out (../shared/ACCEPTANCE.md), so a good measure counts none."""


@dataclass
class Counted:
    """The counted vertices of one frame: index, depth (m, weighted as the measure does), the segment each
    entered (its deepest), and the rest-surface distance to that segment (m, capped at the geodesic ramp)."""

    vertex: np.ndarray
    depth: np.ndarray
    entered: np.ndarray
    geodesic: np.ndarray


def rest_geodesic(character: Character, parts: BodyParts, limit: float) -> torch.Tensor:
    """``(V, S)`` distance along the rest mesh from every vertex to each segment (m; ``inf`` beyond ``limit``)."""
    geo = geodesic_to_parts(character.vertices.double().numpy(), character.faces.numpy().astype(np.int64),
                            parts.vertex_part.numpy(), parts.num_parts, limit)  # fmt: skip
    return torch.from_numpy(geo)


def counted_at(character: Character, parts: BodyParts, sdf: PartSDF, geodesic: torch.Tensor, grot: torch.Tensor,
               gpos: torch.Tensor, tolerance: float) -> tuple[np.ndarray, Counted]:  # fmt: skip
    """Posed vertices ``(V, 3)`` of one frame and its counted vertices (deeper than ``tolerance``);
    ``geodesic`` from :func:`rest_geodesic`."""
    with torch.no_grad():
        posed = character.pose_vertices(grot, gpos)
        samples = sample_pairs(sdf, posed, segment_matrices(character, parts, grot, gpos))
        depth = effective_depth(sdf, samples)
    v_n = character.num_vertices
    best = torch.zeros(v_n)
    seg = torch.full((v_n,), -1, dtype=torch.long)
    order = torch.argsort(depth)  # ascending: the deepest sample of a vertex is written last
    best[samples.vertex[order]] = depth[order]
    seg[samples.vertex[order]] = samples.part[order]
    hot = torch.nonzero(best > tolerance).flatten()
    return posed[0].numpy(), Counted(hot.numpy(), best[hot].numpy(), seg[hot].numpy(), geodesic[hot, seg[hot]].numpy())


def draw_xray(ax: Any, verts: np.ndarray, faces: np.ndarray, counted: Counted, cluster_of: np.ndarray,
              view: tuple[float, float], k180: float, focus: np.ndarray | None = None, radius: float | None = None) -> None:  # fmt: skip
    """The body as faint triangles and the counted vertices as dots coloured by part (size by depth); counted
    vertices within :data:`FOLD_BAND_M` of the part they enter as black crosses."""
    fold_band = FOLD_BAND_M / k180
    v = verts[:, [0, 2, 1]]  # Y-up mesh -> matplotlib z-up
    faces = faces[frame_3d(ax, v, faces, view, focus, radius, zoom=1.45)]
    ax.add_collection3d(Poly3DCollection(v[faces], facecolors=(0.55, 0.58, 0.62, 0.05), edgecolors="none"))
    if len(counted.vertex):
        p = v[counted.vertex]
        colours = [PART_COLORS[CLUSTERS[cluster_of[i]]] for i in counted.vertex]
        size = 3 + 10 * np.clip(counted.depth * k180 * 100 / 3.0, 0, 1)
        ax.scatter(*p.T, c=colours, s=size, depthshade=False, linewidths=0)
        fold = counted.geodesic < fold_band
        if fold.any():  # counted vertices in a joint fold: black crosses (a good measure has none)
            ax.scatter(*p[fold].T, c="black", s=40, marker="x", depthshade=False, linewidths=1.2)


def draw_section(ax: Any, verts: np.ndarray, faces: np.ndarray, face_cluster: np.ndarray, counted: Counted,
                 cluster_of: np.ndarray, origin: np.ndarray, normal: np.ndarray, up: np.ndarray, radius: float, k180: float) -> None:  # fmt: skip
    """Each part's outline in the plane (origin, normal), and the counted vertices within 1 cm of it."""
    normal = normal / np.linalg.norm(normal)
    a = up - normal * (up @ normal)
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    to2d = lambda x: np.stack([(x - origin) @ b, (x - origin) @ a], -1)  # noqa: E731
    for c, name in enumerate(CLUSTERS):
        sel = faces[face_cluster == c]
        if not len(sel):
            continue
        lines = trimesh.intersections.mesh_plane(trimesh.Trimesh(verts, sel, process=False), normal, origin)
        for seg in lines:
            q = to2d(seg)
            if np.abs(q).max() < radius * 1.5:
                ax.plot(q[:, 0], q[:, 1], color=PART_COLORS[name], lw=1.2)
    near = np.abs((verts[counted.vertex] - origin) @ normal) < 0.01
    if near.any():
        q = to2d(verts[counted.vertex[near]])
        colours = [PART_COLORS[CLUSTERS[cluster_of[i]]] for i in counted.vertex[near]]
        ax.scatter(q[:, 0], q[:, 1], c=colours, s=6, edgecolors="black", linewidths=0.3, zorder=5)
    ax.set_xlim(-radius, radius)
    ax.set_ylim(-radius, radius)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)


def summary_lines(counted: Counted, cluster_of: np.ndarray, seg_cluster: np.ndarray, names: list[str], k180: float) -> tuple[list[str], dict]:  # fmt: skip
    """'left_arm in torso: 120 v, max 2.1 cm' lines and the same as a dict (depths in cm at 1.80 m)."""
    rows: dict[str, dict] = {}
    for v, d, s in zip(counted.vertex, counted.depth, counted.entered, strict=True):
        key = f"{CLUSTERS[cluster_of[v]]} in {CLUSTERS[seg_cluster[s]]}"
        r = rows.setdefault(key, {"vertices": 0, "max_cm": 0.0, "segments": set()})
        r["vertices"] += 1
        r["max_cm"] = max(r["max_cm"], float(d) * k180 * 100)
        r["segments"].add(names[s])
    out = {k: {"vertices": r["vertices"], "max_cm": round(r["max_cm"], 2), "into": sorted(r["segments"])} for k, r in rows.items()}
    lines = [f"{k}: {r['vertices']} v, max {r['max_cm']:.1f} cm ({'/'.join(r['into'])})"
             for k, r in sorted(out.items(), key=lambda kv: -kv[1]["vertices"])]  # fmt: skip
    return lines, out


def render_frame(clip: str, character: Character, parts: BodyParts, sdf: PartSDF, geodesic: torch.Tensor, motion: Motion,
                 frame: int, out_dir: Path, suffix: str = "") -> dict[str, Any]:  # fmt: skip
    k180 = 1.80 / character.height
    tol = MetricParams().penetration_tolerance_m / k180
    grot, gpos = motion.slice(frame, frame + 1).global_transforms()
    verts, counted = counted_at(character, parts, sdf, geodesic, grot, gpos, tol)
    faces = character.faces.numpy()
    seg_cluster = np.asarray(parts.cluster)
    cluster_of = seg_cluster[parts.vertex_part.numpy()]
    face_cluster = seg_cluster[parts.face_part.numpy()]  # over parts.faces: the body's, less accessory meshes'
    body_faces = parts.faces.numpy()
    folds = int((counted.geodesic < FOLD_BAND_M / k180).sum())
    lines, table = summary_lines(counted, cluster_of, seg_cluster, parts.names, k180)
    fig = plt.figure(figsize=(17, 4.6), dpi=70)
    hips = parts.index("Hips")
    rest_rot, _ = character.skeleton.rest_global()
    j = parts.joints[hips]
    turn = rotations.mul(grot[0, j], rotations.inv(rest_rot[j]))  # rest -> posed rotation of the hips
    side = rotations.apply(turn, torch.tensor([1.0, 0.0, 0.0])).numpy()  # the body's left-right axis, posed
    side[1] = 0.0
    side /= max(np.linalg.norm(side), 1e-9)
    facing = np.degrees(np.arctan2(side[2], side[0]))  # turn about Y that took the rest body's X here
    views = {"front": (8, 90 + facing), "side": (8, facing)}
    for k, (name, view) in enumerate(views.items()):
        ax = fig.add_subplot(1, 5, k + 1, projection="3d")
        draw_xray(ax, verts, faces, counted, cluster_of, view, k180)
        ax.set_title(name, fontsize=9)
    if len(counted.vertex):
        deepest = counted.vertex[int(np.argmax(counted.depth))]
        origin = verts[deepest]
        radius = 0.22 * character.height / 1.80
        ax = fig.add_subplot(1, 5, 3, projection="3d")
        draw_xray(ax, verts, faces, counted, cluster_of, (18, 45 + facing), k180, origin, radius)
        ax.set_title(f"close-up around the deepest ({counted.depth.max() * k180 * 100:.1f} cm)", fontsize=9)
        ax = fig.add_subplot(1, 5, 4)
        draw_section(ax, verts, body_faces, face_cluster, counted, cluster_of, origin, np.array([0.0, 1.0, 0.0]),
                     np.cross(side, [0.0, 1.0, 0.0]), radius, k180)  # fmt: skip
        ax.set_title("horizontal section through the deepest", fontsize=9)
        ax = fig.add_subplot(1, 5, 5)
        draw_section(ax, verts, body_faces, face_cluster, counted, cluster_of, origin, side, np.array([0.0, 1.0, 0.0]),
                     radius, k180)  # fmt: skip
        ax.set_title("sagittal section through the deepest", fontsize=9)
    handles = [plt.Line2D([], [], color=c, marker="o", lw=0, label=n) for n, c in PART_COLORS.items()]
    if folds:
        handles.append(plt.Line2D([], [], color="black", marker="x", lw=0, label="counted in a joint fold"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    pct = 100.0 * len(counted.vertex) / character.num_vertices
    title = (f"{clip} frame {frame} on {character.name}: {len(counted.vertex)} vertices counted ({pct:.2f} %), "
             f"in joint folds (< 3 cm along the surface from the part entered): {folds}")  # fmt: skip
    fig.suptitle(title + (f" [fold band {suffix[9:]}]" if suffix else "") + "\n" + "; ".join(lines[:4]), fontsize=9)
    fig.subplots_adjust(left=0.01, right=0.99, top=0.84, bottom=0.1, wspace=0.08)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"pen_{clip}_{character.name}_f{frame}{suffix}.png"
    fig.savefig(path)
    plt.close(fig)
    return {"clip": clip, "body": character.name, "frame": frame, "counted": len(counted.vertex),
            "percent": round(pct, 3), "fold_vertices": folds, "by_pair": table, "png": str(path)}  # fmt: skip


def pick_frames(character: Character, mapping: JointMapping, sdf: PartSDF, motion: Motion, count: int,
                gap: int = 15) -> list[int]:  # fmt: skip
    """The ``count`` frames with the most counted vertices, at least ``gap`` frames apart."""
    m = measure_clip(character, mapping, sdf, motion)
    tol = MetricParams().penetration_tolerance_m * character.height / 1.80
    per_frame = (m.vertex_depth > tol).sum(-1)
    chosen: list[int] = []
    for f in torch.argsort(per_frame, descending=True).tolist():
        if all(abs(f - c) >= gap for c in chosen):
            chosen.append(f)
        if len(chosen) == count:
            break
    return sorted(chosen)


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("motion", type=Path)
    ap.add_argument("--body", action="append", required=True, help="target body (file or builtin:<preset>)")
    ap.add_argument("--frames", type=int, nargs="*", default=[])
    ap.add_argument("--auto", type=int, default=0, help="also draw the N frames that count the most vertices")
    ap.add_argument("--max-frames", type=int, default=300)
    ap.add_argument("--dead-zone-cm", type=float, default=None,
                    help="the geodesic ramp's fold band (SDFParams.geodesic_dead_zone_m, cm at 1.80 m) to draw with; "
                    "0 draws what the measure counted before the band existed")  # fmt: skip
    ap.add_argument("-o", "--out-dir", type=Path, default=results_dir("diag"), help="where the PNGs go")
    args = ap.parse_args()
    torch.set_num_threads(1)
    loaded = load_clip(args.motion, JUDGE_FPS, args.max_frames)
    source = loaded.motion
    for body in args.body:
        tgt = load_character(body)
        ch = tgt.character
        parts, sdf = part_sdf_for(ch, tgt.mapping)
        suffix = ""
        if args.dead_zone_cm is not None:
            sdf = build_part_sdf(ch, parts, SDFParams(geodesic_dead_zone_m=args.dead_zone_cm / 100.0))
            suffix = f"_deadzone{args.dead_zone_cm:g}cm"
        motion = copy_retarget(source, loaded.mapping, ch.skeleton, tgt.mapping)
        geodesic = rest_geodesic(ch, parts, 2 * FOLD_BAND_M * ch.height / 1.80)
        frames = list(args.frames)
        if args.auto:
            frames += [f for f in pick_frames(ch, tgt.mapping, sdf, motion, args.auto) if f not in frames]
        for f in frames:
            print(json.dumps(render_frame(args.motion.stem, ch, parts, sdf, geodesic, motion, f, args.out_dir, suffix)))


if __name__ == "__main__":
    main()
