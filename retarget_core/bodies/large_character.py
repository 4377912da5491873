"""A generated studio-sized character: about 100k vertices in five skinned meshes, written as a GLB.

Made from a built-in MakeHuman body (:func:`retarget_core.bodies.presets.load_preset`) and trimesh:

- ``Body``: the body subdivided (every triangle split in four at its edge midpoints, weights averaged);
- ``Shirt``: the subdivided body's torso and upper-arm triangles, subdivided once more and pushed 1.2 cm out
  along the normals (an open garment over the torso);
- ``EyeLeft``, ``EyeRight``: spheres set in the head behind the face;
- ``Teeth``: a capsule inside the mouth.

Every mesh but the body is skinned by copying the nearest body vertex's weights. Used by the large-character
test and by ``benchmarks/bench/large_character_benchmark.py``; nothing is stored in the repository.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib
import torch
import trimesh
from scipy.spatial import cKDTree

from retarget_core.character import Character
from retarget_core.io.gltf_write import build_gltf

TORSO_JOINTS = ("Hips", "Spine", "Spine1", "Spine2", "LeftShoulder", "RightShoulder", "LeftArm", "RightArm")
SHIRT_OFFSET_M = 0.012
EYE_RADIUS_M = 0.012
INFLUENCES = 4


@dataclass
class Piece:
    """One mesh of the character: vertices ``(N, 3)``, triangles ``(T, 3)``, dense skin weights ``(N, J)``."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray


def subdivide(vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every triangle in four at its edge midpoints (shared edges share a midpoint); a midpoint's weights
    are the mean of its edge's two ends. Returns vertices, faces and weights."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = len(vertices) + inverse.reshape(3, -1).T  # (T, 3): midpoints of edges 01, 12, 20
    verts = np.concatenate([vertices, vertices[uniq].mean(1)])
    w = np.concatenate([weights, weights[uniq].mean(1)])
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return verts, new, w


def _nearest_weights(body: Piece, points: np.ndarray) -> np.ndarray:
    """Dense weights ``(N, J)`` of the body vertex nearest each point ``(N, 3)``."""
    _, idx = cKDTree(body.vertices).query(points, k=1)
    return body.weights[idx]


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)


def _shirt(body: Piece, names: list[str], scale: float) -> Piece:
    """The torso and upper-arm triangles of ``body`` (dominant joint among :data:`TORSO_JOINTS`), once more
    subdivided and offset outward."""
    torso = [names.index(n) for n in TORSO_JOINTS if n in names]
    dominant = body.weights.argmax(1)
    keep = np.isin(dominant[body.faces], torso).all(1)
    used, local = np.unique(body.faces[keep], return_inverse=True)
    verts, faces, w = subdivide(body.vertices[used], local.reshape(-1, 3), body.weights[used])
    verts = verts + SHIRT_OFFSET_M * scale * _vertex_normals(verts, faces)
    return Piece("Shirt", verts, faces, _nearest_weights(body, verts))


def _face_front(body: Piece, head: np.ndarray, x: float, y: float, band: float) -> float:
    """The largest z of the head vertices within ``band`` of (x, y) (the face's surface there)."""
    v = body.vertices[head]
    near = (np.abs(v[:, 0] - x) < band) & (np.abs(v[:, 1] - y) < band)
    return float(v[near, 2].max()) if near.any() else float(v[:, 2].max())


def _head_pieces(body: Piece, names: list[str], scale: float) -> list[Piece]:
    """Two eyes and the teeth, inside the head (placed from the head vertices' extent)."""
    head = np.nonzero(body.weights.argmax(1) == names.index("Head"))[0]
    v = body.vertices[head]
    lo, hi = v.min(0), v.max(0)
    eye_y = lo[1] + 0.62 * (hi[1] - lo[1])
    centre_x = 0.5 * (lo[0] + hi[0])
    out = []
    r = EYE_RADIUS_M * scale
    for name, side in (("EyeLeft", 1.0), ("EyeRight", -1.0)):
        x = centre_x + side * 0.032 * scale
        z = _face_front(body, head, x, eye_y, 0.01 * scale) - 1.4 * r
        eye = trimesh.creation.icosphere(subdivisions=4, radius=r)
        verts = np.asarray(eye.vertices) + [x, eye_y, z]
        out.append(Piece(name, verts, np.asarray(eye.faces), _nearest_weights(body, verts)))
    mouth_y = eye_y - 0.075 * scale
    z = _face_front(body, head, centre_x, mouth_y, 0.01 * scale) - 0.025 * scale
    teeth = trimesh.creation.capsule(height=0.03 * scale, radius=0.007 * scale, count=[48, 48])
    teeth.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    verts = np.asarray(teeth.vertices) + [centre_x, mouth_y, z]
    out.append(Piece("Teeth", verts, np.asarray(teeth.faces), _nearest_weights(body, verts)))
    return out


def large_character_pieces(preset: str = "male_average") -> tuple[Character, list[Piece]]:
    """The body (as a Character, for its skeleton) and the five meshes of the large character."""
    from retarget_core.bodies.presets import load_preset

    base = load_preset(preset)
    dense = base.dense_weights().numpy().astype(np.float64)
    verts, faces, w = subdivide(base.vertices.numpy().astype(np.float64), base.faces.numpy(), dense)
    body = Piece("Body", verts, faces, w)
    scale = base.height / 1.80
    names = list(base.skeleton.names)
    return base, [body, _shirt(body, names, scale), *_head_pieces(body, names, scale)]


def _sparse(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`INFLUENCES` largest weights of each row ``(N, J)``, renormalised: joints, weights ``(N, 4)``."""
    idx = np.argsort(-weights, axis=1)[:, :INFLUENCES]
    w = np.take_along_axis(weights, idx, 1)
    return idx, w / np.maximum(w.sum(1, keepdims=True), 1e-12)


def _merged(base: Character, pieces: list[Piece]) -> Character:
    """All pieces as one Character (the layout the GLB reader rebuilds)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces])
    joints, weights = zip(*(_sparse(p.weights) for p in pieces), strict=True)
    return Character(
        name="large_character",
        skeleton=base.skeleton,
        vertices=torch.from_numpy(np.concatenate([p.vertices for p in pieces])).float(),
        faces=torch.from_numpy(np.concatenate([p.faces + o for p, o in zip(pieces, offsets, strict=False)])).long(),
        skin_joints=torch.from_numpy(np.concatenate(joints)).long(),
        skin_weights=torch.from_numpy(np.concatenate(weights)).float(),
    )


def _append(gltf: pygltflib.GLTF2, blob: bytearray, values: np.ndarray, component: int, kind: str,
            target: int, bounds: bool = False) -> int:  # fmt: skip
    """Add ``values`` to ``blob`` as a new buffer view and accessor of ``gltf``; returns the accessor index."""
    dtype = {5126: "<f4", 5121: "<u1", 5123: "<u2", 5125: "<u4"}[component]
    arr = np.ascontiguousarray(values, dtype=dtype)
    blob.extend(b"\0" * (-len(blob) % 4))
    gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=arr.nbytes, target=target))
    blob.extend(arr.tobytes())
    acc = pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, byteOffset=0, componentType=component,
                             count=int(arr.shape[0]), type=kind)  # fmt: skip
    if bounds:
        flat = arr.reshape(arr.shape[0], -1)
        acc.min, acc.max = [float(x) for x in flat.min(0)], [float(x) for x in flat.max(0)]
    gltf.accessors.append(acc)
    return len(gltf.accessors) - 1


def _add_mesh(gltf: pygltflib.GLTF2, blob: bytearray, piece: Piece) -> None:
    """A skinned mesh node for ``piece`` (the skin of the body, skin 0)."""
    joints, weights = _sparse(piece.weights)
    attrs = pygltflib.Attributes(
        POSITION=_append(gltf, blob, piece.vertices, 5126, "VEC3", 34962, bounds=True),
        NORMAL=_append(gltf, blob, _vertex_normals(piece.vertices, piece.faces), 5126, "VEC3", 34962),
        JOINTS_0=_append(gltf, blob, joints, 5121, "VEC4", 34962),
        WEIGHTS_0=_append(gltf, blob, weights, 5126, "VEC4", 34962),
    )
    indices = _append(gltf, blob, piece.faces.reshape(-1), 5125, "SCALAR", 34963)
    gltf.meshes.append(pygltflib.Mesh(name=piece.name, primitives=[pygltflib.Primitive(attributes=attrs, indices=indices, material=0)]))
    gltf.nodes.append(pygltflib.Node(name=piece.name, mesh=len(gltf.meshes) - 1, skin=0))
    gltf.scenes[0].nodes.append(len(gltf.nodes) - 1)


def write_large_character(path: str | Path, preset: str = "male_average") -> Path:
    """Write the large character (see the module doc) as a GLB at ``path``; returns the path."""
    base, pieces = large_character_pieces(preset)
    body = _merged(base, pieces[:1])
    body.name = pieces[0].name
    gltf = build_gltf(body)
    blob = bytearray(gltf.binary_blob())
    for piece in pieces[1:]:
        _add_mesh(gltf, blob, piece)
    blob.extend(b"\0" * (-len(blob) % 4))
    gltf.buffers[0].byteLength = len(blob)
    gltf.set_binary_blob(bytes(blob))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    gltf.save_binary(str(path))
    return path


__all__ = ["Piece", "large_character_pieces", "subdivide", "write_large_character"]
