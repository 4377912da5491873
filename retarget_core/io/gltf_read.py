"""Read glTF 2.0 (``.gltf`` with embedded ``data:`` URIs) and GLB files into a Character and Motions.

Everything is baked into world space, metres, Y up: a joint's world matrix in the rest pose (node TRS of the
joint and of every ancestor, joints or not, e.g. an ``Armature`` node scaled by 0.01 or rotated from Z-up) is
split into rotation + uniform scale + translation; the skeleton keeps rotation and translation only, as local
transforms whose forward kinematics reproduce the world positions and rotations. Rest vertices are the bind-pose
vertices skinned into that rest pose, ``v = sum_k w_k * W_k(rest) * IBM_k * v_bind``: what a glTF viewer shows
with no animation. Animations are sampled at a fixed rate and baked the same way on the same skeleton.

Choices: several skins are merged (union of their joints); every skinned primitive of every mesh node becomes one
mesh; an unskinned mesh node under a joint is attached rigidly to that joint; influences beyond four (``JOINTS_1``
...) are reduced to the four largest and renormalised; scale is dropped from joints (its mean is used for
positions, with a note when it is not uniform).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from retarget_core import kinematics
from retarget_core.character import Character, Material
from retarget_core.config import get_settings
from retarget_core.errors import InvalidFileError, LimitExceededError, UnsupportedFileError
from retarget_core.io.accessors import GltfData, check_extensions, require_finite
from retarget_core.io.vrm import humanoid_canonical, humanoid_extras
from retarget_core.mesh_roles import MeshSpan, with_mesh_roles
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
# Required extensions that do not change what this reader needs (any component type is decoded anyway).
SUPPORTED_EXTENSIONS = {
    "KHR_mesh_quantization",
    "KHR_materials_unlit",
    "KHR_texture_transform",
    "KHR_materials_emissive_strength",
}
COMMON_RATES = (24.0, 25.0, 30.0, 48.0, 50.0, 60.0, 72.0, 90.0, 100.0, 120.0, 144.0, 240.0)
MAX_INFLUENCES = 4
MAX_ANIMATION_CHANNELS = 20_000
"""Most channels one animation may have (a skeleton at the joint limit needs 3 per joint)."""
MAX_COORDINATE = 1e6
"""Largest node translation or translation keyframe (file units): larger is not a character or a motion."""
_VERTEX_CHUNK = 65_536


@dataclass
class GltfContents:
    """What a glTF file holds.

    character: the merged skinned mesh on its baked skeleton, or None when the file has no skinned mesh.
    motions: one per glTF animation, on the same skeleton as ``character`` (when there is one).
    notes: what was simplified, skipped or assumed, for a person to read.
    """

    character: Character | None
    motions: list[Motion] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    humanoid: dict[str, str] = field(default_factory=dict)  # VRM humanoid bones as joint names (io/vrm.py)


# ----- container ------------------------------------------------------------------------------------------------------
def _parse_container(raw: bytes, label: str, notes: list[str]) -> tuple[Any, bytes | None]:
    """The JSON document and the GLB binary chunk (None for .gltf)."""
    if raw[:4] == GLB_MAGIC:
        if len(raw) < 12:
            raise InvalidFileError("truncated GLB: shorter than its 12-byte header", label)
        _, version, length = struct.unpack_from("<4sII", raw)
        if version != 2:
            raise UnsupportedFileError(f"GLB container version {version}: only glTF 2.0 (version 2) is read", label)
        if length > len(raw):
            raise InvalidFileError(f"truncated GLB: the header says {length} bytes but the file has {len(raw)}", label)
        if length < len(raw):
            notes.append(f"{len(raw) - length} bytes after the end of the GLB were ignored")
        pos, chunks = 12, []
        while pos < length:
            if pos + 8 > length:
                raise InvalidFileError(f"truncated GLB: chunk header at byte {pos} runs past the end", label)
            clen, ctype = struct.unpack_from("<II", raw, pos)
            if pos + 8 + clen > length:
                raise InvalidFileError(
                    f"truncated GLB: chunk at byte {pos} of {clen} bytes runs past the end ({length})", label
                )
            chunks.append((ctype, pos + 8, clen))
            pos += 8 + clen
        if not chunks or chunks[0][0] != CHUNK_JSON:
            raise InvalidFileError("malformed GLB: the first chunk is not the JSON chunk", label)
        # Some exporters pad the JSON chunk with NUL instead of spaces: tolerate it.
        text = raw[chunks[0][1] : chunks[0][1] + chunks[0][2]].rstrip(b"\x00 \t\r\n")
        bins = [c for c in chunks[1:] if c[0] == CHUNK_BIN]
        bin_chunk = raw[bins[0][1] : bins[0][1] + bins[0][2]] if bins else None
    else:
        text = raw[3:] if raw[:3] == b"\xef\xbb\xbf" else raw
        if not text.lstrip()[:1] == b"{":
            raise InvalidFileError("not a glTF file: neither the GLB magic 'glTF' nor a JSON object", label)
        bin_chunk = None
    try:
        doc = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise InvalidFileError(f"the glTF JSON cannot be parsed: {exc}", label) from exc
    return doc, bin_chunk


# ----- transforms (numpy, float64) ------------------------------------------------------------------------------------
def _compose(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """4x4 matrices ``(..., 4, 4)`` ``T * R * S`` from ``(..., 3)``, ``(..., 4)`` xyzw, ``(..., 3)``."""
    batch = t.shape[:-1]
    r = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*batch, 3, 3)
    m = np.zeros((*batch, 4, 4))
    m[..., :3, :3] = r * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def _decompose(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Translation, xyzw rotation and per-axis scale of one affine 4x4 matrix (a reflection goes into scale x)."""
    a = m[:3, :3]
    s = np.linalg.norm(a, axis=0)
    if (s < 1e-12).any():
        s = np.where(s < 1e-12, 1.0, s)
    if np.linalg.det(a) < 0:
        s[0] = -s[0]
    q = Rotation.from_matrix(_orthonormal(a / s)).as_quat()
    return m[:3, 3].copy(), q, s


def _orthonormal(a: np.ndarray) -> np.ndarray:
    """The nearest proper rotations ``(..., 3, 3)`` to ``a`` (polar decomposition)."""
    u, _, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


def _quat_slerp(a: np.ndarray, b: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Shortest-arc slerp between xyzw quaternions ``(n, 4)`` at fractions ``(n,)``."""
    dot = (a * b).sum(-1)
    b = np.where(dot[:, None] < 0, -b, b)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    small = sin < 1e-6
    safe = np.where(small, 1.0, sin)
    wa = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    wb = np.where(small, u, np.sin(u * theta) / safe)
    q = wa[:, None] * a + wb[:, None] * b
    return q / np.linalg.norm(q, axis=-1, keepdims=True).clip(min=1e-12)


# ----- node hierarchy ------------------------------------------------------------------------------------------------
@dataclass
class _Nodes:
    """The node tree: parents, a parent-before-child order and the rest TRS of every node."""

    parents: list[int]
    order: list[int]
    rank: dict[int, int]
    t: np.ndarray  # (N, 3)
    q: np.ndarray  # (N, 4) xyzw
    s: np.ndarray  # (N, 3)
    names: list[Any]

    def ancestors(self, n: int) -> list[int]:
        out, p = [], self.parents[n]
        while p >= 0:
            out.append(p)
            p = self.parents[p]
        return out

    def with_ancestors(self, chosen: set[int]) -> set[int]:
        """``chosen`` and every ancestor of its nodes, in time linear in the result (a walk up stops at a node
        already taken: its ancestors are taken, or will be when it is reached itself)."""
        out = set(chosen)
        for node in chosen:
            p = self.parents[node]
            while p >= 0 and p not in out:
                out.add(p)
                p = self.parents[p]
        return out


def _read_nodes(data: GltfData, notes: list[str]) -> _Nodes:
    nodes = data.array("nodes")
    n = len(nodes)
    parents = [-1] * n
    t, q, s = np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), np.ones((n, 3))
    names: list[Any] = []
    children_of: list[list[int]] = []
    for i in range(n):
        node = data.item("nodes", i, f"nodes[{i}]")
        names.append(node.get("name"))
        kids = node.get("children", [])
        if not isinstance(kids, list):
            raise data.fail(f"nodes[{i}].children must be an array")
        kids = [data.index(c, n, f"nodes[{i}].children") for c in kids]
        for c in kids:
            if parents[c] != -1 or c == i:
                raise data.fail(
                    f"node {c} has more than one parent (or is its own child): the node graph is not a tree"
                )
            parents[c] = i
        children_of.append(kids)
        if "matrix" in node:
            m = data.get_floats(node, "matrix", 16, f"nodes[{i}]", []).reshape(4, 4).T
            t[i], q[i], s[i] = _decompose(m)
        else:
            t[i] = data.get_floats(node, "translation", 3, f"nodes[{i}]", [0.0, 0.0, 0.0])
            if float(np.abs(t[i]).max()) > MAX_COORDINATE:
                raise data.fail(f"nodes[{i}].translation is {float(np.abs(t[i]).max()):.3g} from its parent, over "
                                f"the limit of {MAX_COORDINATE:g}")
            qi = data.get_floats(node, "rotation", 4, f"nodes[{i}]", [0.0, 0.0, 0.0, 1.0])
            norm = float(np.linalg.norm(qi))
            if norm < 1e-6:
                raise data.fail(f"nodes[{i}].rotation is not a unit quaternion ({qi.tolist()})")
            q[i] = qi / norm
            s[i] = data.get_floats(node, "scale", 3, f"nodes[{i}]", [1.0, 1.0, 1.0])
    order: list[int] = []
    stack = [i for i in range(n) if parents[i] == -1][::-1]
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(children_of[i][::-1])
    if len(order) != n:
        raise data.fail("the node hierarchy has a cycle")
    return _Nodes(parents, order, {node: k for k, node in enumerate(order)}, t, q, s, names)


def _world(nodes: _Nodes, needed: list[int], t: np.ndarray, q: np.ndarray, s: np.ndarray) -> dict[int, np.ndarray]:
    """World matrices ``(F, 4, 4)`` of ``needed`` (closed under ancestors) from per-node TRS ``(F, N, .)``."""
    needed_sorted = sorted(needed, key=nodes.rank.__getitem__)
    local = _compose(t[:, needed_sorted], q[:, needed_sorted], s[:, needed_sorted])
    world: dict[int, np.ndarray] = {}
    for k, node in enumerate(needed_sorted):
        p = nodes.parents[node]
        world[node] = local[:, k] if p < 0 else world[p] @ local[:, k]
    return world


def _with_ancestors(nodes: _Nodes, chosen: set[int]) -> list[int]:
    return list(nodes.with_ancestors(chosen))


def _bake(world: np.ndarray, notes: list[str], what: str) -> tuple[np.ndarray, np.ndarray]:
    """World rotations ``(..., 4)`` xyzw and positions ``(..., 3)`` of world matrices ``(..., 4, 4)``, dropping scale."""
    a = world[..., :3, :3]
    sv = np.linalg.svd(a, compute_uv=False)
    if (sv.max(-1) > sv.min(-1) * (1 + 1e-3)).any():
        notes.append(f"{what}: non-uniform scale in the joint transforms was replaced by its mean")
    if (np.linalg.det(a) < 0).any():
        notes.append(f"{what}: mirrored (negative-scale) joint transforms were replaced by the nearest rotation")
    rot = _orthonormal(a)
    quat = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(*rot.shape[:-2], 4)
    return quat, world[..., :3, 3].copy()


def _unique_names(nodes: _Nodes, chosen: list[int]) -> list[str]:
    out: list[str] = []
    used: set[str] = set()
    for node in chosen:
        raw = nodes.names[node]
        base = raw.strip() if isinstance(raw, str) and raw.strip() else f"joint_{node}"
        name, k = base, 2
        while name in used:
            name, k = f"{base}_{k}", k + 1
        used.add(name)
        out.append(name)
    return out


def _make_skeleton(
    nodes: _Nodes, joint_nodes: list[int], notes: list[str], attach: dict[int, int] | None = None
) -> Skeleton:
    """A baked skeleton of ``joint_nodes`` (sorted parent-before-child) from the rest node TRS. ``attach``: joint
    node -> the joint node it hangs from instead of its nearest joint ancestor (see :func:`_detached_parents`)."""
    chosen = set(joint_nodes)
    parents = []
    for node in joint_nodes:
        p = nodes.parents[node]
        while p >= 0 and p not in chosen:
            p = nodes.parents[p]
        p = (attach or {}).get(node, p)
        parents.append(joint_nodes.index(p) if p >= 0 else -1)
    world = _world(nodes, _with_ancestors(nodes, chosen), nodes.t[None], nodes.q[None], nodes.s[None])
    quat, pos = _bake(np.stack([world[n][0] for n in joint_nodes]), notes, "rest pose")
    rot, trans = kinematics.global_to_local(
        parents, torch.as_tensor(quat, dtype=torch.float64), torch.as_tensor(pos, dtype=torch.float64)
    )
    return Skeleton(_unique_names(nodes, joint_nodes), parents, trans.float(), rot.float())


def _skeleton_nodes(nodes: _Nodes, skins: list[_Skin], animated: set[int], notes: list[str]) -> list[int]:
    """The nodes that become joints, parent-before-child: every skin joint and the nodes between two of them;
    without a skin, the animated nodes, their ancestors and their descendants."""
    if skins:
        joints = set().union(*(s.joints for s in skins))
        chosen = set(joints)
        no_joint_above: set[int] = set()  # nodes with no joint among their ancestors (walks stop there)
        for j in joints:
            path_up: list[int] = []
            p = nodes.parents[j]
            while p >= 0 and p not in no_joint_above:
                if p in joints:
                    chosen.update(path_up)
                    break
                path_up.append(p)
                p = nodes.parents[p]
            else:
                no_joint_above.update(path_up)
        if len(skins) > 1:
            notes.append(f"{len(skins)} skins merged into one skeleton (union of their joints)")
    else:
        chosen = nodes.with_ancestors(animated)
        for n in nodes.order:  # descendants: parent-before-child order makes one pass enough
            if nodes.parents[n] in chosen:
                chosen.add(n)
    return sorted(chosen, key=nodes.rank.__getitem__)


# ----- skins and meshes ----------------------------------------------------------------------------------------------
@dataclass
class _Skin:
    joints: list[int]  # node indices
    ibm: np.ndarray  # (len(joints), 4, 4)


def _read_skins(data: GltfData, n_nodes: int) -> list[_Skin]:
    skins = []
    for i, _ in enumerate(data.array("skins")):
        skin = data.item("skins", i, f"skins[{i}]")
        joints = skin.get("joints")
        if not isinstance(joints, list) or not joints:
            raise data.fail(f"skins[{i}].joints must be a non-empty array")
        joints = [data.index(j, n_nodes, f"skins[{i}].joints") for j in joints]
        if "inverseBindMatrices" in skin:
            ibm = data.accessor(skin["inverseBindMatrices"], f"skins[{i}].inverseBindMatrices", allowed_types=("MAT4",))
            ibm = require_finite(ibm.astype(np.float64), f"skins[{i}].inverseBindMatrices", data.label)
            if ibm.shape[0] < len(joints):
                raise data.fail(f"skins[{i}] has {len(joints)} joints but only {ibm.shape[0]} inverse bind matrices")
        else:
            ibm = np.tile(np.eye(4), (len(joints), 1, 1))
        skins.append(_Skin(joints, ibm[: len(joints)]))
    return skins


def limit_influences(joints: np.ndarray, weights: np.ndarray, k: int = MAX_INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest influences per vertex ``(V, k)`` from ``(V, K)`` joint indices and weights: repeated
    joints are summed, rows renormalised to 1 (float32), unused slots get joint 0 and weight 0."""
    by_joint = np.argsort(joints, axis=1, kind="stable")
    joints = np.take_along_axis(joints.astype(np.int64), by_joint, 1)
    weights = np.take_along_axis(weights.astype(np.float64), by_joint, 1)
    n = joints.shape[1]
    for c in range(n - 1, 0, -1):  # sum runs of the same joint into the run's first slot
        same = joints[:, c] == joints[:, c - 1]
        weights[same, c - 1] += weights[same, c]
        weights[same, c] = 0.0
    if n < k:
        joints = np.concatenate([joints, np.zeros((joints.shape[0], k - n), np.int64)], 1)
        weights = np.concatenate([weights, np.zeros((weights.shape[0], k - n))], 1)
    order = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    joints = np.take_along_axis(joints, order, 1)
    weights = np.take_along_axis(weights, order, 1)
    joints[weights <= 0] = 0
    weights = np.clip(weights, 0.0, None)
    total = weights.sum(1, keepdims=True)
    weights = weights / np.where(total > 0, total, 1.0)
    return joints, weights.astype(np.float32)


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray:
    """Triangles ``(T, 3)`` from the index list of a TRIANGLES (4), TRIANGLE_STRIP (5) or TRIANGLE_FAN (6) primitive."""
    if mode == 4:
        return idx[: len(idx) - len(idx) % 3].reshape(-1, 3)
    if len(idx) < 3:
        return np.zeros((0, 3), np.int64)
    i = np.arange(len(idx) - 2)
    if mode == 5:
        odd = i % 2
        tri = np.stack([idx[i], idx[i + 1 + odd], idx[i + 2 - odd]], 1)
    else:
        tri = np.stack([idx[i + 1], idx[i + 2], np.full_like(i, idx[0])], 1)
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    return tri[keep]


@dataclass
class _MeshParts:
    vertices: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    joints: list[np.ndarray] = field(default_factory=list)
    weights: list[np.ndarray] = field(default_factory=list)
    uvs: list[np.ndarray | None] = field(default_factory=list)
    material: int | None = None
    num_vertices: int = 0
    num_faces: int = 0


def _skin_rest(positions: np.ndarray, joints: np.ndarray, weights: np.ndarray, mats: np.ndarray) -> np.ndarray:
    """Positions ``(V, 3)`` skinned by per-joint matrices ``(J, 4, 4)`` with influences ``(V, K)`` (float64)."""
    out = np.empty_like(positions)
    mats3 = mats[:, :3, :]
    total = weights.sum(1, keepdims=True)
    weights = weights / np.where(total > 0, total, 1.0)
    for start in range(0, positions.shape[0], _VERTEX_CHUNK):
        sl = slice(start, start + _VERTEX_CHUNK)
        blend = np.einsum("vk,vkij->vij", weights[sl], mats3[joints[sl]])
        out[sl] = np.einsum("vij,vj->vi", blend[:, :, :3], positions[sl]) + blend[:, :, 3]
    return out


def _read_primitive(
    data: GltfData, prim: Any, where: str, parts: _MeshParts, notes: list[str]
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]] | None:
    """Positions ``(V, 3)``, triangles ``(T, 3)`` (local to the primitive) and the attribute dict, or None when
    the primitive is skipped."""
    settings = get_settings()
    if not isinstance(prim, dict):
        raise data.fail(f"{where} must be an object")
    mode = prim.get("mode", 4)
    if mode not in (0, 1, 2, 3, 4, 5, 6):
        raise data.fail(f"{where}.mode = {mode!r} is not a glTF primitive mode")
    if mode < 4:
        notes.append(f"{where}: points/lines primitive (mode {mode}) skipped")
        return None
    attrs = prim.get("attributes")
    if not isinstance(attrs, dict) or "POSITION" not in attrs:
        notes.append(f"{where}: no POSITION attribute, skipped")
        return None
    count = data.accessor_count(attrs["POSITION"], f"{where}.attributes.POSITION")
    if parts.num_vertices + count > settings.max_vertices:
        raise LimitExceededError(f"more than {settings.max_vertices} vertices (max_vertices)", data.label)
    pos = data.accessor(attrs["POSITION"], f"{where}.attributes.POSITION", allowed_types=("VEC3",)).astype(np.float64)
    require_finite(pos, f"{where} POSITION", data.label)
    if "indices" in prim:
        icount = data.accessor_count(prim["indices"], f"{where}.indices")
        if parts.num_faces + icount // 3 > settings.max_triangles and mode == 4:
            raise LimitExceededError(f"more than {settings.max_triangles} triangles (max_triangles)", data.label)
        idx = data.accessor(prim["indices"], f"{where}.indices", allowed_types=("SCALAR",))
        if idx.dtype.kind != "u":
            raise data.fail(f"{where}.indices must be an unsigned integer accessor")
        idx = idx.astype(np.int64)
        if idx.size and idx.max() >= count:
            raise data.fail(f"{where}.indices has the index {int(idx.max())}, out of range for {count} vertices")
    else:
        idx = np.arange(count, dtype=np.int64)
    if mode == 4 and len(idx) % 3:
        notes.append(f"{where}: {len(idx) % 3} trailing indices that make no full triangle ignored")
    tri = _triangles(mode, idx)
    if parts.num_faces + len(tri) > settings.max_triangles:
        raise LimitExceededError(f"more than {settings.max_triangles} triangles (max_triangles)", data.label)
    return pos, tri, attrs


def _attribute(
    data: GltfData, attrs: dict[str, Any], name: str, count: int, where: str, types: tuple[str, ...]
) -> np.ndarray:
    values = data.accessor(attrs[name], f"{where}.attributes.{name}", allowed_types=types)
    if values.shape[0] != count:
        raise data.fail(f"{where}.attributes.{name} has {values.shape[0]} elements but POSITION has {count}")
    return values


def _influences(
    data: GltfData, attrs: dict[str, Any], count: int, n_skin_joints: int, where: str, notes: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """All ``JOINTS_n``/``WEIGHTS_n`` sets of a skinned primitive as ``(V, 4n)`` skin-joint indices and weights."""
    joints, weights = [], []
    k = 0
    while f"JOINTS_{k}" in attrs and f"WEIGHTS_{k}" in attrs:
        j = _attribute(data, attrs, f"JOINTS_{k}", count, where, ("VEC4",))
        if j.dtype.kind not in "u":
            raise data.fail(f"{where}.attributes.JOINTS_{k} must be UNSIGNED_BYTE or UNSIGNED_SHORT, not normalized")
        w = _attribute(data, attrs, f"WEIGHTS_{k}", count, where, ("VEC4",)).astype(np.float64)
        require_finite(w, f"{where} WEIGHTS_{k}", data.label)
        j = j.astype(np.int64)
        used = w > 0
        if (j[used] >= n_skin_joints).any():
            raise data.fail(
                f"{where}.attributes.JOINTS_{k} has the joint {int(j[used].max())}, but the skin has {n_skin_joints} joints"
            )
        j[~used] = 0
        joints.append(j)
        weights.append(w)
        k += 1
    if not joints:
        raise data.fail(f"{where} belongs to a skinned mesh node but has no JOINTS_0/WEIGHTS_0")
    jj, ww = np.concatenate(joints, 1), np.concatenate(weights, 1)
    if (ww < 0).any():
        notes.append(f"{where}: negative skinning weights set to 0")
        ww = np.clip(ww, 0.0, None)
    empty = ww.sum(1) <= 0
    if empty.any():
        notes.append(
            f"{where}: {int(empty.sum())} vertices without any skinning weight bound to the skin's first joint"
        )
        ww[empty, 0] = 1.0
        jj[empty, 0] = 0
    return jj, ww


@dataclass
class _MeshNode:
    """How one mesh node is bound: its mesh, its skin (None when rigid) or the joint it rides on rigidly."""

    node: int
    mesh_index: int
    mesh: dict[str, Any]
    skin: _Skin | None
    rigid_joint: int | None


def _mesh_node(
    data: GltfData, nodes: _Nodes, n: int, skins: list[_Skin], node_to_joint: dict[int, int], notes: list[str]
) -> _MeshNode | None:
    """The binding of node ``n`` when it holds a mesh that can follow the skeleton; None otherwise (noted)."""
    node = data.item("nodes", n, f"nodes[{n}]")
    if "mesh" not in node:
        return None
    mesh = data.item("meshes", node["mesh"], f"nodes[{n}].mesh")
    if not isinstance(mesh.get("primitives"), list):
        raise data.fail(f"meshes[{node['mesh']}].primitives must be an array")
    skin = skins[data.index(node["skin"], len(skins), f"nodes[{n}].skin")] if "skin" in node else None
    rigid_joint = None
    if skin is None:
        rigid_joint = next((node_to_joint[a] for a in [n, *nodes.ancestors(n)] if a in node_to_joint), None)
        if rigid_joint is None:
            notes.append(f"mesh node {nodes.names[n] or n} is not skinned and not under a joint: skipped")
            return None
    return _MeshNode(n, node["mesh"], mesh, skin, rigid_joint)


def _bound_vertices(
    data: GltfData,
    binding: _MeshNode,
    pos: np.ndarray,
    attrs: dict[str, Any],
    where: str,
    rest_world: dict[int, np.ndarray],
    node_to_joint: dict[int, int],
    notes: list[str],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest vertices ``(V, 3)`` and their skeleton joints and weights ``(V, 4)`` of one primitive: skinned into
    the rest pose, or placed by the mesh node's rest matrix and bound wholly to its rigid joint."""
    count = pos.shape[0]
    if binding.skin is not None:
        skin = binding.skin
        jj, ww = _influences(data, attrs, count, len(skin.joints), where, notes)
        mats = np.stack([rest_world[j][0] for j in skin.joints]) @ skin.ibm
        verts = _skin_rest(pos, jj, ww, mats)
        skin_to_skel = np.array([node_to_joint[j] for j in skin.joints], dtype=np.int64)
        jj, ww = limit_influences(skin_to_skel[jj], ww)
        return verts, jj, ww
    m = rest_world[binding.node][0]
    verts = pos @ m[:3, :3].T + m[:3, 3]
    jj = np.zeros((count, MAX_INFLUENCES), np.int64)
    jj[:, 0] = binding.rigid_joint
    ww = np.zeros((count, MAX_INFLUENCES), np.float32)
    ww[:, 0] = 1.0
    return verts, jj, ww


def _add_mesh_node(
    data: GltfData,
    binding: _MeshNode,
    rest_world: dict[int, np.ndarray],
    node_to_joint: dict[int, int],
    parts: _MeshParts,
    notes: list[str],
) -> None:
    """Append every triangle primitive of one mesh node to ``parts``."""
    for p, prim in enumerate(binding.mesh["primitives"]):
        where = f"meshes[{binding.mesh_index}].primitives[{p}]"
        got = _read_primitive(data, prim, where, parts, notes)
        if got is None:
            continue
        pos, tri, attrs = got
        verts, jj, ww = _bound_vertices(data, binding, pos, attrs, where, rest_world, node_to_joint, notes)
        uv = None
        if "TEXCOORD_0" in attrs:
            uv = _attribute(data, attrs, "TEXCOORD_0", pos.shape[0], where, ("VEC2",)).astype(np.float32)
            require_finite(uv, f"{where} TEXCOORD_0", data.label)
        parts.vertices.append(verts)
        parts.faces.append(tri + parts.num_vertices)
        parts.joints.append(jj)
        parts.weights.append(ww)
        parts.uvs.append(uv)
        parts.num_vertices += pos.shape[0]
        parts.num_faces += len(tri)
        if parts.material is None and isinstance(prim, dict) and "material" in prim:
            parts.material = data.index(prim["material"], len(data.array("materials")), f"{where}.material")


def _merged_uvs(parts: _MeshParts, notes: list[str]) -> torch.Tensor | None:
    """UVs ``(V, 2)`` of all primitives (zeros for those without TEXCOORD_0), or None when none has them."""
    if all(u is None for u in parts.uvs):
        return None
    if any(u is None for u in parts.uvs):
        notes.append("some primitives have no TEXCOORD_0: their UVs were set to 0")
    return torch.from_numpy(
        np.concatenate(
            [
                u if u is not None else np.zeros((v.shape[0], 2), np.float32)
                for u, v in zip(parts.uvs, parts.vertices, strict=True)
            ]
        )
    )


def _build_character(
    data: GltfData,
    nodes: _Nodes,
    skins: list[_Skin],
    skeleton_nodes: list[int],
    skeleton: Skeleton,
    name: str,
    notes: list[str],
) -> Character | None:
    """Every mesh node that follows the skeleton (skinned, or rigidly under a joint) merged into one Character;
    None when no mesh is skinned."""
    settings = get_settings()
    node_to_joint = {node: j for j, node in enumerate(skeleton_nodes)}
    rest_world = _world(
        nodes, _with_ancestors(nodes, set(range(len(nodes.parents)))), nodes.t[None], nodes.q[None], nodes.s[None]
    )
    parts = _MeshParts()
    spans: list[MeshSpan] = []
    any_skinned = False
    for n in nodes.order:
        binding = _mesh_node(data, nodes, n, skins, node_to_joint, notes)
        if binding is None:
            continue
        span_start = (parts.num_vertices, parts.num_faces)
        _add_mesh_node(data, binding, rest_world, node_to_joint, parts, notes)
        if parts.num_vertices > span_start[0]:  # one span per mesh node, for the mesh roles (mesh_roles.py)
            any_skinned = any_skinned or binding.skin is not None
            # the node's name first: it names the instance (Witch_Body), the mesh its data (Cube.040)
            label = str(nodes.names[n] or binding.mesh.get("name") or f"mesh {binding.mesh_index}")
            spans.append(MeshSpan(label, span_start[0], parts.num_vertices - span_start[0], span_start[1],
                                  parts.num_faces - span_start[1]))  # fmt: skip
    if not any_skinned:
        if parts.vertices:
            notes.append("no skinned mesh: rigid meshes under joints are not a character on their own")
        return None
    uvs = _merged_uvs(parts, notes)
    if parts.num_vertices > settings.max_vertices:
        raise LimitExceededError(
            f"{parts.num_vertices} vertices, over the limit of {settings.max_vertices}", data.label
        )
    character = Character(
        name=name,
        skeleton=skeleton,
        vertices=torch.from_numpy(np.concatenate(parts.vertices)).float(),
        faces=torch.from_numpy(np.concatenate(parts.faces)).long(),
        skin_joints=torch.from_numpy(np.concatenate(parts.joints)).long(),
        skin_weights=torch.from_numpy(np.concatenate(parts.weights)).float(),
        uvs=uvs,
        material=_read_material(data, parts.material, notes),
    )
    return with_mesh_roles(character, spans)


def _read_material(data: GltfData, index: int | None, notes: list[str]) -> Material:
    if index is None:
        return Material()
    mat = data.item("materials", index, "material")
    pbr = mat.get("pbrMetallicRoughness", {})
    if not isinstance(pbr, dict):
        raise data.fail(f"materials[{index}].pbrMetallicRoughness must be an object")
    where = f"materials[{index}].pbrMetallicRoughness"
    color = data.get_floats(pbr, "baseColorFactor", 4, where, [1.0, 1.0, 1.0, 1.0]).clip(0.0, 1.0)
    metallic = float(
        data.get_floats({"v": [pbr.get("metallicFactor", 1.0)]}, "v", 1, f"{where}.metallicFactor", [1.0])[0]
    )
    rough = float(
        data.get_floats({"v": [pbr.get("roughnessFactor", 1.0)]}, "v", 1, f"{where}.roughnessFactor", [1.0])[0]
    )
    image, mime = None, None
    tex_info = pbr.get("baseColorTexture")
    if isinstance(tex_info, dict) and "index" in tex_info:
        tex = data.item("textures", tex_info["index"], f"{where}.baseColorTexture.index")
        if "source" in tex:
            image, mime = data.image(tex["source"], f"textures[{tex_info['index']}].source")
            if mime is None:
                mime = (
                    "image/png"
                    if image[:8] == b"\x89PNG\r\n\x1a\n"
                    else "image/jpeg"
                    if image[:3] == b"\xff\xd8\xff"
                    else None
                )
        else:
            notes.append(f"textures[{tex_info['index']}] has no core 'source' image: base colour texture dropped")
    return Material(
        base_color=(float(color[0]), float(color[1]), float(color[2]), float(color[3])),
        image_bytes=image,
        image_mime=mime,
        metallic=min(max(metallic, 0.0), 1.0),
        roughness=min(max(rough, 0.0), 1.0),
    )


# ----- joints detached from the body (IK layouts) ----------------------------------------------------------------
IK_REACH = 1.5
"""A detached joint is attached to a leaf of the body at most this many times the leaf's own bone length away."""
IK_ALIGN = 0.5
"""... and in the direction the leaf's bone points (cosine at least this): the detached joint continues it."""


def _detached_parents(character: Character) -> dict[int, int]:
    """Joint -> new parent joint for the deforming joints that hang beside the body from a non-deforming rig root
    (Blender IK layouts, e.g. Quaternius: ``Foot.L`` parented to ``Root``, not to ``LowerLeg.L``): each goes
    below the body's leaf joint whose bone it continues (nearest, within :data:`IK_REACH`, along
    :data:`IK_ALIGN`). The body is the deforming subtree with the most deforming joints; a joint deforms when
    some vertex is weighted to it."""
    sk = character.skeleton
    deforming = set(torch.unique(character.skin_joints[character.skin_weights > 0]).tolist())
    above = {j: set(sk.ancestors(j)) for j in deforming}
    tops = [j for j in sorted(deforming) if not above[j] & deforming]
    if len(tops) < 2:
        return {}
    body = max(tops, key=lambda t: (sum(t == j or t in above[j] for j in deforming), -t))
    has_child = {sk.parents[j] for j in deforming}
    leaves = [j for j in deforming if body in above[j] and j not in has_child]
    pos = sk.rest_global()[1].double()
    out: dict[int, int] = {}
    for t in tops:
        reach = []
        for leaf in leaves if t != body else []:
            bone, gap = pos[leaf] - pos[sk.parents[leaf]], pos[t] - pos[leaf]
            length, dist = float(bone.norm()), float(gap.norm())
            if length > 1e-9 and dist <= IK_REACH * length and float(bone @ gap) >= IK_ALIGN * length * dist:
                reach.append((dist, leaf))
        if reach:
            out[t] = min(reach)[1]
    return out


def _reattached(
    nodes: _Nodes, skeleton_nodes: list[int], character: Character, attach: dict[int, int], notes: list[str]
) -> tuple[list[int], Character]:
    """The skeleton nodes in their new parent-before-child order and ``character`` on the skeleton whose joints
    ``attach`` (joint -> new parent joint) re-parents; skin indices follow the new order."""
    sk = character.skeleton
    parents = [attach.get(j, p) for j, p in enumerate(sk.parents)]
    children: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    order: list[int] = []
    stack = [j for j, p in enumerate(parents) if p < 0][::-1]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(children[j][::-1])
    new_nodes = [skeleton_nodes[j] for j in order]
    by_node = {skeleton_nodes[j]: skeleton_nodes[p] for j, p in attach.items()}
    skeleton = _make_skeleton(nodes, new_nodes, notes, by_node)
    new_index = torch.empty(len(order), dtype=torch.long)
    new_index[torch.tensor(order)] = torch.arange(len(order))
    for j, p in sorted(attach.items()):
        notes.append(f"joint {sk.names[j]!r} hangs beside the body from a rig root (an IK layout): attached below "
                     f"{sk.names[p]!r}, whose bone it continues")  # fmt: skip
    return new_nodes, replace(character, skeleton=skeleton, skin_joints=new_index[character.skin_joints])


# ----- animations ----------------------------------------------------------------------------------------------------
@dataclass
class _Channel:
    node: int
    path: str
    times: np.ndarray  # (n,)
    values: np.ndarray  # (n, d) or (3n, d) for CUBICSPLINE
    interpolation: str


def _read_animation(data: GltfData, a: int, n_nodes: int, notes: list[str]) -> tuple[str, list[_Channel]]:
    anim = data.item("animations", a, f"animations[{a}]")
    where = f"animations[{a}]"
    raw_name = anim.get("name")
    name = raw_name if isinstance(raw_name, str) and raw_name else f"animation_{a}"
    samplers, channels = anim.get("samplers", []), anim.get("channels", [])
    if not isinstance(samplers, list) or not isinstance(channels, list):
        raise data.fail(f"{where}: samplers and channels must be arrays")
    if len(channels) > MAX_ANIMATION_CHANNELS:
        raise LimitExceededError(f"{where} has {len(channels)} channels, over the limit of {MAX_ANIMATION_CHANNELS}",
                                 data.label)
    out: list[_Channel] = []
    for c, ch in enumerate(channels):
        if not isinstance(ch, dict) or not isinstance(ch.get("target"), dict):
            raise data.fail(f"{where}.channels[{c}] must be an object with a target")
        target = ch["target"]
        path = target.get("path")
        if "node" not in target or path not in ("translation", "rotation", "scale"):
            if path == "weights":
                notes.append(f"{name}: morph target weights channel ignored")
            elif "node" in target:
                raise data.fail(f"{where}.channels[{c}].target.path = {path!r} is not a glTF animation path")
            else:
                notes.append(f"{name}: channel {c} without a target node ignored")
            continue
        node = data.index(target["node"], n_nodes, f"{where}.channels[{c}].target.node")
        sampler = samplers[data.index(ch.get("sampler"), len(samplers), f"{where}.channels[{c}].sampler")]
        if not isinstance(sampler, dict):
            raise data.fail(f"{where}.samplers must hold objects")
        interp = sampler.get("interpolation", "LINEAR")
        if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise data.fail(f"{where}: interpolation {interp!r} is not LINEAR, STEP or CUBICSPLINE")
        times = data.accessor(sampler.get("input"), f"{where} sampler input", allowed_types=("SCALAR",)).astype(
            np.float64
        )
        require_finite(times, f"{name} keyframe times", data.label)
        if (np.diff(times) < 0).any():
            raise data.fail(f"{name}: keyframe times must increase")
        size = 4 if path == "rotation" else 3
        values = data.accessor(sampler.get("output"), f"{where} sampler output", allowed_types=(f"VEC{size}",)).astype(
            np.float64
        )
        require_finite(values, f"{name} {path} keyframes", data.label)
        if path == "translation" and values.size and float(np.abs(values).max()) > MAX_COORDINATE:
            raise data.fail(f"{name}: a translation keyframe of node {node} is {float(np.abs(values).max()):.3g} "
                            f"from the origin, over the limit of {MAX_COORDINATE:g} (not a motion in metres)")
        expected = len(times) * (3 if interp == "CUBICSPLINE" else 1)
        if values.shape[0] != expected:
            raise data.fail(
                f"{name}: a {interp} {path} sampler has {values.shape[0]} values for {len(times)} keyframes"
            )
        if path == "rotation" and interp != "CUBICSPLINE":
            norms = np.linalg.norm(values, axis=1)
            if (norms < 1e-6).any():
                raise data.fail(f"{name}: rotation keyframes of zero length")
            values = values / norms[:, None]
        out.append(_Channel(node, path, times, values, interp))
    return name, out


def _sample(ch: _Channel, t: np.ndarray) -> np.ndarray:
    """Values ``(F, d)`` of a channel at times ``(F,)`` (clamped to its keyframe range)."""
    times, n = ch.times, len(ch.times)
    vals = ch.values[1::3] if ch.interpolation == "CUBICSPLINE" else ch.values
    if n == 1:
        return np.repeat(vals[:1], len(t), 0)
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, n - 2)
    td = times[k + 1] - times[k]
    u = np.clip((t - times[k]) / np.where(td > 0, td, 1.0), 0.0, 1.0)
    u = np.where(td > 0, u, (t >= times[k + 1]).astype(np.float64))
    if ch.interpolation == "STEP":
        return vals[np.where(u >= 1.0, k + 1, k)]
    if ch.interpolation == "LINEAR":
        if ch.path == "rotation":
            return _quat_slerp(vals[k], vals[k + 1], u)
        return vals[k] * (1 - u)[:, None] + vals[k + 1] * u[:, None]
    out_tan, in_tan = ch.values[2::3], ch.values[0::3]
    u2, u3 = u * u, u * u * u
    h = [2 * u3 - 3 * u2 + 1, (u3 - 2 * u2 + u) * td, -2 * u3 + 3 * u2, (u3 - u2) * td]
    res = (
        h[0][:, None] * vals[k]
        + h[1][:, None] * out_tan[k]
        + h[2][:, None] * vals[k + 1]
        + h[3][:, None] * in_tan[k + 1]
    )
    if ch.path == "rotation":
        res = res / np.linalg.norm(res, axis=1, keepdims=True).clip(min=1e-12)
    return res


def infer_fps(channels: list[_Channel], default: float) -> float:
    """The clip's rate from the median keyframe step, snapped to a common rate within 3%; else ``default``."""
    steps = np.concatenate([np.diff(ch.times) for ch in channels] or [np.zeros(0)])
    steps = steps[steps > 1e-6]
    if not steps.size:
        return default
    rate = 1.0 / float(np.median(steps))
    best = min(COMMON_RATES, key=lambda r: abs(r - rate) / r)
    return best if abs(best - rate) / best < 0.03 else default


def _build_motion(
    data: GltfData,
    nodes: _Nodes,
    skeleton: Skeleton,
    skeleton_nodes: list[int],
    name: str,
    channels: list[_Channel],
    fps: float | None,
    notes: list[str],
) -> Motion | None:
    settings = get_settings()
    needed = _with_ancestors(nodes, set(skeleton_nodes))
    relevant = set(needed)
    used = [ch for ch in channels if ch.node in relevant]
    if len(used) < len(channels):
        notes.append(f"{name}: {len(channels) - len(used)} channels on nodes outside the skeleton ignored")
    if not used:
        notes.append(f"{name}: no channel animates the skeleton; animation skipped")
        return None
    rate = float(fps) if fps is not None else infer_fps(used, settings.default_fps)
    duration = max(float(ch.times[-1]) for ch in used)
    duration = max(duration, 0.0)
    frames_f = duration * rate
    if not math.isfinite(frames_f) or frames_f + 1 > settings.max_frames:
        raise LimitExceededError(
            f"animation {name!r} lasts {duration:g} s: more than {settings.max_frames} frames at {rate:g} fps (max_frames)",
            data.label,
        )
    frames = int(math.floor(frames_f + 1e-3)) + 1
    n_nodes = len(nodes.parents)
    data.budget.charge(frames * (n_nodes * 10 * 8 + len(needed) * 16 * 8 * 2 + len(skeleton_nodes) * 7 * 8 * 4),
                       f"animation {name!r} ({frames} frames of {n_nodes} nodes)")
    t = np.arange(frames, dtype=np.float64) / rate
    tt = np.repeat(nodes.t[None], frames, 0)
    qq = np.repeat(nodes.q[None], frames, 0)
    ss = np.repeat(nodes.s[None], frames, 0)
    for ch in used:
        target = {"translation": tt, "rotation": qq, "scale": ss}[ch.path]
        target[:, ch.node] = _sample(ch, t)
    if any(ch.path == "scale" and ch.node in set(skeleton_nodes) for ch in used):
        notes.append(f"{name}: joint scale animation is baked into positions; joints carry no scale")
    world = _world(nodes, needed, tt, qq, ss)
    quat, pos = _bake(np.stack([world[n] for n in skeleton_nodes], axis=1), notes, name)
    rot, trans = kinematics.global_to_local(
        skeleton.parents, torch.as_tensor(quat, dtype=torch.float64), torch.as_tensor(pos, dtype=torch.float64)
    )
    return Motion(skeleton, rate, rot.float(), trans.float(), name)


# ----- entry points --------------------------------------------------------------------------------------------------
def load_gltf_data(path: str | Path, notes: list[str] | None = None) -> GltfData:
    """The parsed, size-checked document and buffers of a .glb or .gltf file (no other file is opened)."""
    settings = get_settings()
    path = Path(path)
    label = str(path)
    size = path.stat().st_size
    if size > settings.max_file_bytes:
        raise LimitExceededError(
            f"the file has {size} bytes, over the limit of {settings.max_file_bytes} (max_file_bytes)", label
        )
    raw = path.read_bytes()
    doc, bin_chunk = _parse_container(raw, label, notes if notes is not None else [])
    if not isinstance(doc, dict):
        raise InvalidFileError("the glTF JSON is not an object", label)
    asset = doc.get("asset")
    version = asset.get("version") if isinstance(asset, dict) else None
    if not isinstance(version, str) or not version.startswith("2."):
        raise UnsupportedFileError(f"asset.version is {version!r}: only glTF 2.0 is read", label)
    check_extensions(doc, SUPPORTED_EXTENSIONS, label)
    return GltfData(doc, bin_chunk, max_elements=settings.max_accessor_elements, label=label)


def read_gltf(path: str | Path, *, fps: float | None = None, with_motions: bool = True) -> GltfContents:
    """Read a .glb or .gltf file: its skinned mesh as one Character (or None) and each animation as a Motion,
    all baked to world space in metres on one skeleton. ``fps``: sampling rate of the motions (default: inferred
    from the keyframes); ``with_motions=False``: the animations are checked but not baked (a target character's
    clips are not used). Raises InvalidFileError (or a subclass) for malformed, hostile or over-limit files."""
    settings = get_settings()
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, not {fps!r}")
    path = Path(path)
    notes: list[str] = []
    data = load_gltf_data(path, notes)
    nodes = _read_nodes(data, notes)
    skins = _read_skins(data, len(nodes.parents))
    animations = [_read_animation(data, a, len(nodes.parents), notes) for a in range(len(data.array("animations")))]

    animated = {ch.node for _, chans in animations for ch in chans}
    skeleton_nodes = _skeleton_nodes(nodes, skins, animated, notes)
    if len(skeleton_nodes) > settings.max_joints:
        raise LimitExceededError(
            f"{len(skeleton_nodes)} joints, over the limit of {settings.max_joints} (max_joints)", data.label
        )
    if not skeleton_nodes:
        has_mesh = any(isinstance(n, dict) and "mesh" in n for n in data.array("nodes"))
        notes.append(
            "the file has no skin" + (": its meshes are not a character" if has_mesh else "") + " and no animation"
        )
        return GltfContents(None, [], notes)
    skeleton = _make_skeleton(nodes, skeleton_nodes, notes)

    character = None
    if skins:
        character = _build_character(data, nodes, skins, skeleton_nodes, skeleton, path.stem, notes)
        if character is None:
            notes.append("the skins are used by no mesh: no character")
        elif attach := _detached_parents(character):
            skeleton_nodes, character = _reattached(nodes, skeleton_nodes, character, attach, notes)
            skeleton = character.skeleton
    elif data.array("meshes"):
        notes.append(
            f"{path.name} has no skin: its meshes are not a character (a target character must be a skinned mesh)"
        )
    motions = []
    for name, channels in animations if with_motions else []:
        motion = _build_motion(data, nodes, skeleton, skeleton_nodes, name, channels, fps, notes)
        if motion is not None:
            motions.append(motion)
    node_joint = dict(zip(skeleton_nodes, skeleton.names, strict=True))
    humanoid = {**humanoid_canonical(data.doc, node_joint), **humanoid_extras(data.doc, node_joint)}
    return GltfContents(character, motions, list(dict.fromkeys(notes)), humanoid)


def read_gltf_character(path: str | Path) -> Character:
    """The skinned character of a .glb/.gltf file; InvalidFileError when the file has none."""
    contents = read_gltf(path, with_motions=False)
    if contents.character is None:
        name = Path(path).name
        raise InvalidFileError(f"{name} has no skin: a target character must be a skinned mesh", str(path))
    return contents.character


__all__ = ["GltfContents", "infer_fps", "limit_influences", "load_gltf_data", "read_gltf", "read_gltf_character"]
