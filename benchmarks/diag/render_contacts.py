"""Render a frame with its detected hand self-contacts (and optionally penetration on a target) to a PNG.

A check a person can look at: the source body posed at one frame, contact vertices as red dots joined by lines
(the 3 closest pairs of each contact), hand groups tinted; with ``--target`` a second row shows the copy
baseline on that body with penetrating vertices coloured by depth.

    python benchmarks/diag/render_contacts.py ../shared/data/motions/cmu/002_08.bvh -o contacts.png
    python benchmarks/diag/render_contacts.py CLIP --frame 120 --target ../shared/data/characters/mh_male_bulky.glb

Needs matplotlib (``pip install matplotlib``).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

from retarget_core.body_parts import body_parts  # noqa: E402
from retarget_core.contacts.self_contact import detect_self_contacts  # noqa: E402
from retarget_core.copy_retarget import copy_retarget  # noqa: E402
from retarget_core.energy.sdf import build_part_sdf, sample_pairs, segment_matrices, vertex_depths  # noqa: E402
from retarget_core.loading import load_character, load_motion  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository, for benchmarks.common
from benchmarks.common import frame_3d, parser, results_dir  # noqa: E402

VIEWS = {"front": (10, 90), "side": (10, 0), "three-quarter": (20, 45)}


def draw_mesh(ax: Any, verts: np.ndarray, faces: np.ndarray, face_rgb: np.ndarray, view: tuple[float, float],
              focus: np.ndarray | None = None, radius: float | None = None) -> None:  # fmt: skip
    """Shaded triangles on a 3D axis; the viewer's Y-up mesh is drawn with matplotlib's Z up. ``focus`` and
    ``radius`` (metres, Y-up coordinates) zoom onto a region; triangles outside it are left out."""
    v = verts[:, [0, 2, 1]]  # x, z, y -> matplotlib (x, y, z-up)
    keep = frame_3d(ax, v, faces, view, focus, radius)
    faces, face_rgb = faces[keep], face_rgb[keep]
    tri = v[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
    elev, azim = np.radians(view[0]), np.radians(view[1])
    light = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    shade = 0.35 + 0.65 * np.abs(n @ light)
    ax.add_collection3d(Poly3DCollection(tri, facecolors=np.clip(face_rgb * shade[:, None], 0, 1), edgecolors="none"))


def draw_pairs(ax: Any, x: np.ndarray, pairs: np.ndarray) -> None:
    """Contact pairs as red dots (hand side) and dark red triangles (other side) joined by lines."""
    if len(pairs) == 0:
        return
    p = x[:, [0, 2, 1]]
    ax.scatter(*p[pairs[:, 0]].T, c="red", s=30, depthshade=False, zorder=10)
    ax.scatter(*p[pairs[:, 1]].T, c="darkred", s=30, marker="^", depthshade=False, zorder=10)
    ax.add_collection3d(Line3DCollection(np.stack([p[pairs[:, 0]], p[pairs[:, 1]]], 1), colors="red", linewidths=2))


def render(motion_path: Path, source: str, frame: int | None, out: Path, target: str | None, max_frames: int) -> dict:
    loaded = load_motion(motion_path)
    src = load_character(source)
    sc = src.character
    parts = body_parts(sc, src.mapping)
    motion = copy_retarget(loaded.motion, loaded.mapping, sc.skeleton, src.mapping).slice(0, max_frames)
    grot, gpos = motion.global_transforms()
    posed = sc.pose_vertices(grot, gpos)
    contacts = detect_self_contacts(parts, posed, sc.height, motion.fps)
    if frame is None:
        counts = torch.bincount(contacts.frame, minlength=motion.num_frames) if contacts.count else torch.zeros(1)
        frame = int(counts.argmax())
    sel = contacts.frame == frame
    rows = 2 if target else 1
    fig = plt.figure(figsize=(20, 5.5 * rows), dpi=80)
    faces = sc.faces.numpy()
    x = posed[frame].numpy()
    rgb = np.tile(np.array([0.78, 0.78, 0.8]), (len(faces), 1))
    for h in ("LeftHand", "RightHand"):
        if parts.find(h) is not None:
            rgb[(parts.face_part == parts.index(h)).numpy()] = [0.55, 0.7, 0.95]
    pairs = contacts.pairs[sel].reshape(-1, 2).numpy()
    labels = [f"{contacts.part_names[h]}-{contacts.part_names[o]}" for h, o in zip(contacts.hand[sel].tolist(), contacts.other[sel].tolist(), strict=True)]
    for k, (name, view) in enumerate(VIEWS.items()):
        ax = fig.add_subplot(rows, 4, k + 1, projection="3d")
        draw_mesh(ax, x, faces, rgb, view)
        draw_pairs(ax, x, pairs)
        ax.set_title(name, fontsize=10)
    if len(pairs):
        ax = fig.add_subplot(rows, 4, 4, projection="3d")
        draw_mesh(ax, x, faces, rgb, VIEWS["three-quarter"], x[pairs.ravel()].mean(0), 0.15)
        draw_pairs(ax, x, pairs)
        ax.set_title("close-up (30 cm box)", fontsize=10)
    fig.suptitle(
        f"{motion_path.name} frame {frame} on {sc.name}: {int(sel.sum())} contacts "
        f"({', '.join(sorted(set(labels))) or 'none'}); clip total {contacts.count} in "
        f"{int(contacts.frames_with_contact().sum())}/{motion.num_frames} frames",
        fontsize=11,
    )
    info = {"frame": frame, "contacts_in_frame": sorted(set(labels)), "contacts_total": contacts.count}
    if target:
        tgt = load_character(target)
        tc = tgt.character
        tparts = body_parts(tc, tgt.mapping)
        sdf = build_part_sdf(tc, tparts)
        tm = copy_retarget(loaded.motion, loaded.mapping, tc.skeleton, tgt.mapping).slice(frame, frame + 1)
        tr, tp = tm.global_transforms()
        tv = tc.pose_vertices(tr, tp)
        depth = vertex_depths(sdf, sample_pairs(sdf, tv, segment_matrices(tc, tparts, tr, tp)), 1)[0].numpy()
        fd = depth[tc.faces.numpy()].max(1) * sdf.scale_to_180 * 100  # cm at 1.80 m
        cmap = plt.get_cmap("autumn_r")  # yellow (shallow) to red (deep)
        trgb = np.tile(np.array([0.78, 0.78, 0.8]), (len(fd), 1))
        hot = fd > 0.3
        trgb[hot] = np.asarray(cmap(0.25 + 0.75 * np.clip(fd[hot] / 8.0, 0, 1)))[:, :3]
        for k, (name, view) in enumerate(VIEWS.items()):
            ax = fig.add_subplot(rows, 4, 5 + k, projection="3d")
            draw_mesh(ax, tv[0].numpy(), tc.faces.numpy(), trgb, view)
            ax.set_title(f"{name}: copy onto {tc.name}", fontsize=10)
        ax = fig.add_subplot(rows, 4, 8)
        ax.hist(fd[fd > 0.3], bins=30, color="darkorange")
        ax.set_title(f"penetrating triangles by depth (max {fd.max():.1f} cm at 1.80 m)", fontsize=10)
        ax.set_xlabel("depth, cm at 1.80 m (colour: yellow shallow to red 8 cm or more)")
        info["target_max_penetration_cm_at_180"] = float(fd.max())
    fig.subplots_adjust(left=0.01, right=0.99, top=0.92, bottom=0.06, wspace=0.02, hspace=0.1)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return info


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("motion", type=Path)
    ap.add_argument("--source", default="builtin:male_average", help="source body (file or builtin:<preset>)")
    ap.add_argument("--frame", type=int, default=None, help="frame to draw (default: the one with most contacts)")
    ap.add_argument("--target", default=None, help="also draw the copy baseline's penetration on this body")
    ap.add_argument("--max-frames", type=int, default=10_000)
    ap.add_argument("-o", "--output", type=Path, default=None,
                    help="the PNG (default: benchmarks/diag/results/contacts_<clip>.png)")
    args = ap.parse_args()
    out = args.output or results_dir("diag") / f"contacts_{args.motion.stem}.png"
    info = render(args.motion, args.source, args.frame, out, args.target, args.max_frames)
    print(out, info)


if __name__ == "__main__":
    main()
