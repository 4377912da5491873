"""Write a Character, optionally animated by a Motion, as one self-contained GLB (glTF 2.0) with pygltflib.

Layout: the scene's root nodes are the skeleton's root joint(s) and the mesh node beside them (a skinned mesh
node must not sit under a joint, and its own transform is ignored by glTF). Joint ``j`` is node ``j`` with the
skeleton's rest translation and rotation; the skin's inverse bind matrices are the inverses of the rest world
matrices, so the written mesh (the character's rest vertices) shows unchanged when no animation plays. The
animation keys, at ``i / fps``, the rotation of every joint that moves (the roots always, with their translation,
so the clip keeps its full length) and the translation of every joint whose offset moves. A joint the motion
holds still is written once: no channel when it stays at its node's rest transform, else a single key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib
import torch

from retarget_core import rotations as rot
from retarget_core.character import Character
from retarget_core.io.gltf_read import MAX_INFLUENCES, limit_influences
from retarget_core.motion import Motion

FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
GENERATOR = "retarget_core"
CONSTANT_TOLERANCE = 1e-7  # a track whose values stay this close to its first frame's is written once


class _Blob:
    """One binary buffer of 4-byte aligned buffer views, with the accessors pointing into it."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[pygltflib.BufferView] = []
        self.accessors: list[pygltflib.Accessor] = []

    def view(self, payload: bytes, target: int | None = None) -> int:
        self.data.extend(b"\0" * (-len(self.data) % 4))
        self.views.append(
            pygltflib.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(payload), target=target)
        )
        self.data.extend(payload)
        return len(self.views) - 1

    def accessor(
        self, values: np.ndarray, component: int, kind: str, *, target: int | None = None, bounds: bool = False
    ) -> int:
        dtype = {FLOAT: "<f4", UBYTE: "<u1", USHORT: "<u2", UINT: "<u4"}[component]
        arr = np.ascontiguousarray(values, dtype=dtype)
        acc = pygltflib.Accessor(
            bufferView=self.view(arr.tobytes(), target),
            byteOffset=0,
            componentType=component,
            count=int(arr.shape[0]),
            type=kind,
        )
        if bounds:
            flat = arr.reshape(arr.shape[0], -1)
            acc.min = [float(x) for x in flat.min(0)]
            acc.max = [float(x) for x in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def finish(self) -> bytes:
        self.data.extend(b"\0" * (-len(self.data) % 4))
        return bytes(self.data)


def _weights_float32(weights: np.ndarray) -> np.ndarray:
    """Rows renormalised in float32 so that their float32 sum is 1: the rounding error goes on the largest weight."""
    w = weights.astype(np.float32)
    w = w / w.sum(1, keepdims=True)
    largest = w.argmax(1)
    rows = np.arange(w.shape[0])
    others = w.sum(1, dtype=np.float32) - w[rows, largest]
    w[rows, largest] = np.float32(1.0) - others
    return w


def _normals(character: Character) -> np.ndarray:
    n = character.vertex_normals().detach().double().numpy()
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-8, n / np.where(length > 1e-8, length, 1.0), np.array([0.0, 1.0, 0.0]))
    return n.astype(np.float32)


def _continuous(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(F, 4)`` with signs flipped so consecutive frames lie in the same hemisphere."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True).clip(min=1e-12)
    if len(q) > 1:
        flips = np.cumprod(np.where((q[1:] * q[:-1]).sum(-1) < 0, -1.0, 1.0))
        q[1:] *= flips[:, None]
    return q


def _motion_tracks(character: Character, motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations ``(F, J, 4)`` and translations ``(F, J, 3)`` for the character's joints (matched by name;
    joints the motion lacks keep their rest transform)."""
    sk = character.skeleton
    frames = motion.num_frames
    rots = np.repeat(sk.rest_rotations.detach().double().numpy()[None], frames, 0)
    trans = np.repeat(sk.rest_translations.detach().double().numpy()[None], frames, 0)
    mrot = motion.rotations.detach().double().numpy()
    mtrans = motion.translations.detach().double().numpy()
    matched = 0
    for j, name in enumerate(sk.names):
        m = motion.skeleton.find(name)
        if m is not None:
            rots[:, j] = mrot[:, m]
            trans[:, j] = mtrans[:, m]
            matched += 1
    if matched == 0:
        raise ValueError(f"the motion {motion.name!r} animates none of the joints of {character.name!r}")
    return rots, trans


def _check(character: Character, motion: Motion | None) -> None:
    """ValueError for what would make an invalid file: non-finite values, faces or joints out of range."""
    tensors = {"vertices": character.vertices, "skin_weights": character.skin_weights}
    tensors.update({"uvs": character.uvs} if character.uvs is not None else {})
    if motion is not None:
        tensors.update({"motion rotations": motion.rotations, "motion translations": motion.translations})
    for what, t in tensors.items():
        if not torch.isfinite(t).all():
            raise ValueError(f"{character.name}: {what} contain NaN or infinite values")
    v = character.num_vertices
    if character.faces.numel() and (int(character.faces.min()) < 0 or int(character.faces.max()) >= v):
        raise ValueError(f"{character.name}: faces refer to vertices outside 0..{v - 1}")
    j = character.skin_joints
    if j.numel() and (int(j.min()) < 0 or int(j.max()) >= character.skeleton.num_joints):
        raise ValueError(f"{character.name}: skin joints outside 0..{character.skeleton.num_joints - 1}")
    if (character.skin_weights.sum(1) <= 0).any() or (character.skin_weights < 0).any():
        raise ValueError(f"{character.name}: skin weights must be non-negative with a positive sum per vertex")


def _primitive(character: Character, blob: _Blob) -> pygltflib.Primitive:
    """The skinned mesh's triangles: positions, normals, UVs when present, four joints and weights per vertex."""
    positions = character.vertices.detach().numpy().astype(np.float32)
    joints, weights = limit_influences(
        character.skin_joints.detach().numpy(), character.skin_weights.detach().numpy(), MAX_INFLUENCES
    )
    attributes = pygltflib.Attributes(
        POSITION=blob.accessor(positions, FLOAT, "VEC3", target=ARRAY_BUFFER, bounds=True),
        NORMAL=blob.accessor(_normals(character), FLOAT, "VEC3", target=ARRAY_BUFFER),
    )
    if character.uvs is not None:
        attributes.TEXCOORD_0 = blob.accessor(character.uvs.detach().numpy(), FLOAT, "VEC2", target=ARRAY_BUFFER)
    joint_type = UBYTE if character.skeleton.num_joints < 256 else USHORT
    attributes.JOINTS_0 = blob.accessor(joints, joint_type, "VEC4", target=ARRAY_BUFFER)
    attributes.WEIGHTS_0 = blob.accessor(_weights_float32(weights), FLOAT, "VEC4", target=ARRAY_BUFFER)
    faces = character.faces.detach().numpy().reshape(-1)
    indices = blob.accessor(
        faces, USHORT if character.num_vertices <= 65535 else UINT, "SCALAR", target=ELEMENT_ARRAY_BUFFER
    )
    return pygltflib.Primitive(attributes=attributes, indices=indices, material=0, mode=4)


def _image_mime(image: bytes | None, mime: str | None) -> str | None:
    """The image's MIME type: the one given, else PNG or JPEG by its signature, else None."""
    if not image or mime is not None:
        return mime
    if image[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    return "image/jpeg" if image[:3] == b"\xff\xd8\xff" else None


def _material(
    character: Character, blob: _Blob
) -> tuple[pygltflib.Material, list[pygltflib.Image], list[pygltflib.Texture]]:
    """The material, with the base-colour image only when the mesh has UVs and the image is PNG or JPEG."""
    mat = character.material
    pbr = pygltflib.PbrMetallicRoughness(
        baseColorFactor=[float(c) for c in mat.base_color],
        metallicFactor=float(mat.metallic),
        roughnessFactor=float(mat.roughness),
    )
    images, textures = [], []
    mime = _image_mime(mat.image_bytes, mat.image_mime)
    if mat.image_bytes and character.uvs is not None and mime in ("image/png", "image/jpeg"):
        images.append(pygltflib.Image(bufferView=blob.view(mat.image_bytes), mimeType=mime))
        textures.append(pygltflib.Texture(source=0))
        pbr.baseColorTexture = pygltflib.TextureInfo(index=0)
    material = pygltflib.Material(name=f"{character.name}_material", pbrMetallicRoughness=pbr, doubleSided=False)
    return material, images, textures


def _inverse_bind_matrices(character: Character) -> np.ndarray:
    """``(J, 4, 4)`` inverses of the joints' rest world matrices."""
    grot, gpos = character.skeleton.rest_global()
    world = np.zeros((character.skeleton.num_joints, 4, 4))
    world[:, :3, :3] = rot.to_matrix(rot.normalize(grot.detach().double())).numpy()
    world[:, :3, 3] = gpos.detach().double().numpy()
    world[:, 3, 3] = 1.0
    ibm = np.linalg.inv(world)
    ibm[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return ibm


def _skeleton(character: Character, blob: _Blob) -> tuple[list[pygltflib.Node], pygltflib.Skin, list[int]]:
    """Joint nodes at their rest transforms then the mesh node, the skin, and the root joints."""
    sk = character.skeleton
    num_joints = sk.num_joints
    rest_rot = rot.normalize(sk.rest_rotations.detach().double())
    ibm = _inverse_bind_matrices(character)
    ibm_accessor = blob.accessor(ibm.transpose(0, 2, 1).reshape(num_joints, 16), FLOAT, "MAT4")
    nodes = [
        pygltflib.Node(
            name=name,
            translation=[float(x) for x in sk.rest_translations[j].tolist()],
            rotation=[float(x) for x in rest_rot[j].tolist()],
            children=sk.children(j),
        )
        for j, name in enumerate(sk.names)
    ]
    nodes.append(pygltflib.Node(name=character.name, mesh=0, skin=0))
    roots = [j for j, p in enumerate(sk.parents) if p < 0]
    skin = pygltflib.Skin(
        name=f"{character.name}_skin", inverseBindMatrices=ibm_accessor, joints=list(range(num_joints))
    )
    if len(roots) == 1:
        skin.skeleton = roots[0]
    return nodes, skin, roots


def build_gltf(character: Character, motion: Motion | None = None, *, clip_name: str = "retarget") -> pygltflib.GLTF2:
    """The glTF document (with its binary blob set) of ``character``, animated by ``motion`` when given."""
    _check(character, motion)
    blob = _Blob()
    primitive = _primitive(character, blob)
    material, images, textures = _material(character, blob)
    nodes, skin, roots = _skeleton(character, blob)
    animations = [_animation(character, motion, blob, clip_name)] if motion is not None else []
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator=GENERATOR),
        scene=0,
        scenes=[pygltflib.Scene(name=character.name, nodes=[*roots, len(nodes) - 1])],
        nodes=nodes,
        meshes=[pygltflib.Mesh(name=character.name, primitives=[primitive])],
        skins=[skin],
        materials=[material],
        textures=textures,
        images=images,
        animations=animations,
        accessors=blob.accessors,
        bufferViews=blob.views,
    )
    data = blob.finish()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(data))]
    gltf.set_binary_blob(data)
    return gltf


def _animation(character: Character, motion: Motion, blob: _Blob, clip_name: str) -> pygltflib.Animation:
    sk = character.skeleton
    rots, trans = _motion_tracks(character, motion)
    frames = rots.shape[0]
    if frames == 0:
        raise ValueError("the motion has no frames")
    times = (np.arange(frames, dtype=np.float64) / float(motion.fps)).astype(np.float32)
    time_accessor = blob.accessor(times, FLOAT, "SCALAR", bounds=True)
    rest_t = sk.rest_translations.detach().double().numpy()
    samplers, channels = [], []

    def channel(node: int, path: str, values: np.ndarray, kind: str) -> None:
        samplers.append(
            pygltflib.AnimationSampler(
                input=time_accessor, output=blob.accessor(values, FLOAT, kind), interpolation="LINEAR"
            )
        )
        channels.append(
            pygltflib.AnimationChannel(
                sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path=path)
            )
        )

    rest_r = rot.normalize(sk.rest_rotations.detach().double()).numpy()
    single_key: list[int] = []  # the one-key time accessor, made when first needed

    def once(node: int, path: str, value: np.ndarray, kind: str) -> None:
        if not single_key:
            single_key.append(blob.accessor(np.zeros(1, np.float32), FLOAT, "SCALAR", bounds=True))
        samplers.append(
            pygltflib.AnimationSampler(
                input=single_key[0], output=blob.accessor(value[None], FLOAT, kind), interpolation="LINEAR"
            )
        )
        channels.append(pygltflib.AnimationChannel(
            sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path=path)))  # fmt: skip

    for j in range(sk.num_joints):
        q = _continuous(rots[:, j])
        if sk.parents[j] < 0 or not _constant(q):
            channel(j, "rotation", q, "VEC4")
        elif min(np.abs(q[0] - rest_r[j]).max(), np.abs(q[0] + rest_r[j]).max()) > CONSTANT_TOLERANCE:
            once(j, "rotation", q[0], "VEC4")  # held away from its rest rotation: one key
        if sk.parents[j] < 0:
            channel(j, "translation", trans[:, j], "VEC3")  # the roots carry the clip's full length
        elif np.abs(trans[:, j] - rest_t[j]).max() > 1e-6:
            if _constant(trans[:, j]):
                once(j, "translation", trans[0, j], "VEC3")
            else:
                channel(j, "translation", trans[:, j], "VEC3")
    return pygltflib.Animation(name=clip_name, samplers=samplers, channels=channels)


def _constant(values: np.ndarray) -> bool:
    """Whether a track ``(F, d)`` holds one value on every frame (within :data:`CONSTANT_TOLERANCE`)."""
    return bool(np.abs(values - values[:1]).max() <= CONSTANT_TOLERANCE) if len(values) else True


def glb_bytes(character: Character, motion: Motion | None = None, *, clip_name: str = "retarget") -> bytes:
    """The GLB file of :func:`write_glb` as bytes."""
    return b"".join(build_gltf(character, motion, clip_name=clip_name).save_to_bytes())


def write_glb(character: Character, motion: Motion | None, path: str | Path, *, clip_name: str = "retarget") -> None:
    """Write ``character`` (and ``motion`` as one animation named ``clip_name``; None: a static character) to
    ``path`` as a self-contained GLB that the Khronos glTF validator accepts without errors."""
    Path(path).write_bytes(glb_bytes(character, motion, clip_name=clip_name))


__all__ = ["build_gltf", "glb_bytes", "write_glb"]
