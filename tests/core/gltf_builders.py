"""Small pygltflib builders for constructed glTF test cases (skinned tubes, animations, odd accessors)."""

from __future__ import annotations

import base64
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

FLOAT, BYTE, UBYTE, SHORT, USHORT, UINT = 5126, 5120, 5121, 5122, 5123, 5125
DTYPES = {FLOAT: "<f4", BYTE: "<i1", UBYTE: "<u1", SHORT: "<i2", USHORT: "<u2", UINT: "<u4"}
KINDS = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


def trs_matrix(t=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0), s=(1.0, 1.0, 1.0)) -> np.ndarray:
    """4x4 ``T * R * S`` (xyzw quaternion)."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q).as_matrix() * np.asarray(s, dtype=float)[None, :]
    m[:3, 3] = t
    return m


class Builder:
    """Accumulates a glTF document and one binary buffer with pygltflib."""

    def __init__(self) -> None:
        self.gltf = pygltflib.GLTF2(
            asset=pygltflib.Asset(version="2.0", generator="tests"), scene=0, scenes=[pygltflib.Scene(nodes=[])]
        )
        self.blob = bytearray()

    # --- buffers ---
    def view(self, payload: bytes, *, stride: int | None = None, target: int | None = None) -> int:
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        self.gltf.bufferViews.append(
            pygltflib.BufferView(
                buffer=0, byteOffset=len(self.blob), byteLength=len(payload), byteStride=stride, target=target
            )
        )
        self.blob.extend(payload)
        return len(self.gltf.bufferViews) - 1

    def accessor(
        self,
        values: np.ndarray,
        component: int = FLOAT,
        *,
        kind: str | None = None,
        normalized: bool = False,
        stride: int | None = None,
        target: int | None = None,
    ) -> int:
        """An accessor of ``values`` ``(n,)``, ``(n, k)`` or ``(n, 4, 4)`` (matrices written column-major).
        ``stride``: interleave each element with padding up to that many bytes."""
        arr = np.asarray(values)
        if arr.ndim == 3:
            arr = arr.transpose(0, 2, 1).reshape(arr.shape[0], -1)
        arr = np.ascontiguousarray(arr.reshape(arr.shape[0], -1), dtype=DTYPES[component])
        kind = kind or KINDS[arr.shape[1]]
        payload = arr.tobytes()
        if stride is not None:
            rows = arr.view(np.uint8).reshape(arr.shape[0], -1)
            padded = np.zeros((arr.shape[0], stride), np.uint8)
            padded[:, : rows.shape[1]] = rows
            payload = padded.tobytes()
        acc = pygltflib.Accessor(
            bufferView=self.view(payload, stride=stride, target=target), componentType=component, count=arr.shape[0],
            type=kind, normalized=normalized or None,
        )  # fmt: skip
        if component == FLOAT and kind in ("VEC3", "SCALAR") and np.isfinite(arr).all():
            acc.min = arr.min(0).astype(float).tolist()
            acc.max = arr.max(0).astype(float).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def sparse_accessor(
        self, base: np.ndarray | None, count: int, indices: np.ndarray, values: np.ndarray, kind: str
    ) -> int:
        """A FLOAT accessor of ``count`` elements: ``base`` (or zeros when None) with ``values`` at ``indices``."""
        acc = pygltflib.Accessor(componentType=FLOAT, count=count, type=kind)
        if base is not None:
            acc.bufferView = self.view(np.ascontiguousarray(base, dtype="<f4").tobytes())
        acc.sparse = pygltflib.Sparse(
            count=len(indices),
            indices=pygltflib.AccessorSparseIndices(
                bufferView=self.view(np.asarray(indices, "<u2").tobytes()), componentType=USHORT
            ),
            values=pygltflib.AccessorSparseValues(
                bufferView=self.view(np.ascontiguousarray(values, dtype="<f4").tobytes())
            ),
        )
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    # --- scene ---
    def node(self, name: str | None = None, *, parent: int | None = None, **fields) -> int:
        """A node under ``parent`` (or a scene root); ``fields``: translation, rotation, scale, matrix, mesh, skin."""
        self.gltf.nodes.append(
            pygltflib.Node(
                name=name,
                **{
                    k: (list(map(float, v)) if k in ("translation", "rotation", "scale", "matrix") else v)
                    for k, v in fields.items()
                },
            )
        )
        index = len(self.gltf.nodes) - 1
        if parent is None:
            self.gltf.scenes[0].nodes.append(index)
        else:
            self.gltf.nodes[parent].children.append(index)
        return index

    def mesh(self, primitives: list[dict]) -> int:
        prims = []
        for p in primitives:
            prims.append(
                pygltflib.Primitive(
                    attributes=pygltflib.Attributes(**p["attributes"]),
                    indices=p.get("indices"),
                    mode=p.get("mode", 4),
                    material=p.get("material"),
                )
            )
        self.gltf.meshes.append(pygltflib.Mesh(primitives=prims))
        return len(self.gltf.meshes) - 1

    def skin(self, joints: list[int], inverse_bind: np.ndarray | None) -> int:
        ibm = None if inverse_bind is None else self.accessor(inverse_bind.astype(np.float32), kind="MAT4")
        self.gltf.skins.append(pygltflib.Skin(joints=joints, inverseBindMatrices=ibm))
        return len(self.gltf.skins) - 1

    def animation(self, name: str | None, channels: list[tuple[int, str, np.ndarray, np.ndarray, str]]) -> int:
        """``channels``: (node, path, times (n,), values, interpolation)."""
        samplers, chans = [], []
        for node, path, times, values, interp in channels:
            samplers.append(
                pygltflib.AnimationSampler(
                    input=self.accessor(np.asarray(times, np.float32)),
                    output=self.accessor(values),
                    interpolation=interp,
                )
            )
            chans.append(
                pygltflib.AnimationChannel(
                    sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path=path)
                )
            )
        self.gltf.animations.append(pygltflib.Animation(name=name, samplers=samplers, channels=chans))
        return len(self.gltf.animations) - 1

    # --- output ---
    def _finish(self) -> bytes:
        data = bytes(self.blob) + b"\0" * (-len(self.blob) % 4)
        self.gltf.buffers = [pygltflib.Buffer(byteLength=len(data))]
        return data

    def glb_bytes(self) -> bytes:
        self.gltf.set_binary_blob(self._finish())
        return b"".join(self.gltf.save_to_bytes())

    def save_glb(self, path: Path) -> Path:
        path.write_bytes(self.glb_bytes())
        return path

    def save_gltf_embedded(self, path: Path) -> Path:
        """A .gltf JSON file whose buffer is a base64 ``data:`` URI."""
        data = self._finish()
        self.gltf.buffers[0].uri = "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")
        path.write_text(self.gltf.to_json())
        return path


def patch_glb_json(raw: bytes, old: str, new: str) -> bytes:
    """A GLB with ``old`` replaced by ``new`` in its JSON chunk (header and chunk lengths recomputed), to craft
    what pygltflib refuses to write (for example numbers that parse as infinity)."""
    json_len = struct.unpack_from("<I", raw, 12)[0]
    text = raw[20 : 20 + json_len].decode().replace(old, new).encode()
    text += b" " * (-len(text) % 4)
    rest = raw[20 + json_len :]
    return (
        b"glTF"
        + struct.pack("<II", 2, 12 + 8 + len(text) + len(rest))
        + struct.pack("<I", len(text))
        + b"JSON"
        + text
        + rest
    )


@dataclass
class Tube:
    """A skinned tube around a joint chain: bind-space vertices, faces and per-vertex influences."""

    positions: np.ndarray  # (V, 3) bind space
    faces: np.ndarray  # (T, 3)
    joints: np.ndarray  # (V, 4) skin-local joint indices
    weights: np.ndarray  # (V, 4)


def tube_around(points: np.ndarray, radius: float, ring: int = 6) -> Tube:
    """A closed-ended-free tube with one ring of ``ring`` vertices at each point ``(J, 3)`` (the chain runs along
    one axis; rings lie in the plane of the other two). Ring k is weighted 0.75 to joint k and 0.25 to its parent."""
    axis = np.argmax(np.abs(points[-1] - points[0]))
    a, b = [i for i in range(3) if i != axis]
    ang = np.linspace(0, 2 * np.pi, ring, endpoint=False)
    pos, joints, weights = [], [], []
    for k, p in enumerate(points):
        for t in ang:
            v = np.array(p, dtype=float)
            v[a] += radius * np.cos(t)
            v[b] += radius * np.sin(t)
            pos.append(v)
            joints.append([k, max(k - 1, 0), 0, 0])
            weights.append([0.75, 0.25, 0.0, 0.0] if k > 0 else [1.0, 0.0, 0.0, 0.0])
    faces = []
    for k in range(len(points) - 1):
        for i in range(ring):
            p0, p1 = k * ring + i, k * ring + (i + 1) % ring
            q0, q1 = p0 + ring, p1 + ring
            faces += [[p0, p1, q1], [p0, q1, q0]]
    return Tube(np.array(pos), np.array(faces), np.array(joints), np.array(weights))


def add_skinned_chain(
    b: Builder,
    names: list[str],
    offsets: list[tuple[float, float, float]],
    *,
    parent: int | None = None,
    bind_frame: np.ndarray | None = None,
    radius: float = 0.1,
    weight_component: int = FLOAT,
    joint_component: int = USHORT,
) -> tuple[list[int], Tube, int]:
    """A chain of joint nodes (each offset from the previous) under ``parent``, a skin whose bind pose equals the
    rest pose expressed in ``bind_frame`` coordinates (identity: the chain's own coordinates, without the parent's
    transform; pass the parent's world matrix to bind in world space), and a skinned tube mesh node at the scene root.
    Returns the joint nodes, the tube (bind-space vertices) and the mesh node."""
    joints, world, m = [], [], np.eye(4) if bind_frame is None else bind_frame
    for k, (name, off) in enumerate(zip(names, offsets, strict=True)):
        joints.append(b.node(name, parent=parent if k == 0 else joints[-1], translation=off))
        m = m @ trs_matrix(off)
        world.append(m.copy())
    world = np.stack(world)
    tube = tube_around(world[:, :3, 3], radius)
    ibm = np.linalg.inv(world)
    wvals = tube.weights
    if weight_component == USHORT:
        wvals = np.round(tube.weights * 65535)
    elif weight_component == UBYTE:
        wvals = np.round(tube.weights * 255)
    attrs = {
        "POSITION": b.accessor(tube.positions.astype(np.float32)),
        "JOINTS_0": b.accessor(tube.joints, joint_component, kind="VEC4"),
        "WEIGHTS_0": b.accessor(wvals, weight_component, kind="VEC4", normalized=weight_component != FLOAT),
    }
    mesh = b.mesh([{"attributes": attrs, "indices": b.accessor(tube.faces.reshape(-1), UINT)}])
    skin = b.skin(joints, ibm)
    mesh_node = b.node("Body", mesh=mesh, skin=skin)
    return joints, tube, mesh_node
