"""Characters of several meshes: the role of each mesh (body or accessory) and accessories left out of the
measures (docs/meshes.md)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
from torch import Tensor

from retarget_core.bodies import load_preset
from retarget_core.body_cache import body_sdf
from retarget_core.body_parts import body_parts, mapping_by_name
from retarget_core.character import Character
from retarget_core.mesh_roles import MeshSpan, classify_meshes, with_mesh_roles
from retarget_core.metrics.compute import measure_clip, summarize
from retarget_core.motion import Motion


def _piece(body: Character, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, Tensor, Tensor]:
    """The triangles ``faces`` of ``body`` as a mesh of their own: vertices, local faces, skin joints, weights."""
    used, local = np.unique(faces, return_inverse=True)
    return body.vertices.numpy()[used], local.reshape(-1, 3), body.skin_joints[used], body.skin_weights[used]


def _sphere(centre: np.ndarray, radius: float, joint: int, k: int) -> tuple[np.ndarray, np.ndarray, Tensor, Tensor]:
    s = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    v = np.asarray(s.vertices) + centre
    joints = torch.zeros(len(v), k, dtype=torch.long)
    joints[:, 0] = joint
    weights = torch.zeros(len(v), k)
    weights[:, 0] = 1.0
    return v, np.asarray(s.faces), joints, weights


def _assemble(body: Character, pieces: dict[str, tuple]) -> tuple[Character, list[MeshSpan]]:  # type: ignore[type-arg]
    """One Character of the named pieces (in order) and their spans."""
    verts, faces, joints, weights, spans = [], [], [], [], []
    nv = nf = 0
    for name, (v, f, j, w) in pieces.items():
        verts.append(torch.as_tensor(v, dtype=torch.float32))
        faces.append(torch.as_tensor(f, dtype=torch.long) + nv)
        joints.append(j)
        weights.append(w)
        spans.append(MeshSpan(name, nv, len(v), nf, len(f)))
        nv, nf = nv + len(v), nf + len(f)
    ch = Character("assembled", body.skeleton, torch.cat(verts), torch.cat(faces), torch.cat(joints), torch.cat(weights))
    return ch, spans


@pytest.fixture(scope="module")
def average() -> Character:
    return load_preset("male_average")


def test_a_single_mesh_is_the_body(average: Character) -> None:
    roles = classify_meshes(average, [MeshSpan("Body", 0, average.num_vertices, 0, int(average.faces.shape[0]))])
    assert [(m.role, m.reason) for m in roles] == [("body", "the only mesh")]
    assert bool(average.body_vertices.all()) and average.body_faces() is average.faces


def test_roles_of_a_split_body_inner_geometry_a_garment_and_a_prop(average: Character) -> None:
    names = average.skeleton.names
    dominant = average.skin_joints.gather(1, average.skin_weights.argmax(1, keepdim=True))[:, 0]
    head = torch.isin(dominant, torch.tensor([names.index("Head"), names.index("Neck")]))
    faces = average.faces.numpy()
    head_face = head[average.faces].all(1).numpy()
    torso = torch.isin(dominant, torch.tensor([names.index(n) for n in ("Spine1", "Spine2")]))
    torso_face = torso[average.faces].all(1).numpy()
    shirt_v, shirt_f, shirt_j, shirt_w = _piece(average, faces[torso_face])
    normals = trimesh.Trimesh(shirt_v, shirt_f, process=False).vertex_normals
    _, rest = average.skeleton.rest_global()
    chest = rest[names.index("Spine2")].numpy()
    hand = rest[names.index("RightHand")].numpy()
    k = average.skin_joints.shape[1]
    pieces = {
        "Torso": _piece(average, faces[~head_face]),
        "Head": _piece(average, faces[head_face]),
        "Heart": _sphere(chest, 0.04, names.index("Spine2"), k),
        "Shirt": (shirt_v + 0.01 * normals, shirt_f, shirt_j, shirt_w),
        "Ball": _sphere(hand + np.array([0.0, -0.15, 0.0]), 0.05, names.index("RightHand"), k),
    }
    ch, spans = _assemble(average, pieces)
    roles = {m.name: m for m in classify_meshes(ch, spans)}
    assert roles["Torso"].role == "body" and "largest" in roles["Torso"].reason
    assert roles["Head"].role == "body" and "joined" in roles["Head"].reason
    assert roles["Heart"].role == "accessory" and "inner" in roles["Heart"].reason
    assert roles["Shirt"].role == "accessory" and "over" in roles["Shirt"].reason
    assert roles["Ball"].role == "accessory"  # away from the body, small, one joint
    with_mesh_roles(ch, spans)
    assert int(ch.body_vertices.sum()) == spans[0].vertices + spans[1].vertices


def test_accessories_are_not_measured(average: Character) -> None:
    """A sphere deep in the chest skinned to the left hand would be hand vertices inside the torso; as inner
    geometry it is an accessory: in no part, never sampled by the penetration queries, depth 0, and the shares
    are of body vertices."""
    from retarget_core.energy.sdf import sample_pairs, segment_matrices

    names = average.skeleton.names
    mapping = mapping_by_name(names)
    _, rest = average.skeleton.rest_global()
    k = average.skin_joints.shape[1]
    body = (average.vertices.numpy(), average.faces.numpy(), average.skin_joints, average.skin_weights)
    inner = _sphere(rest[names.index("Spine1")].numpy(), 0.05, names.index("LeftHand"), k)
    ch, spans = _assemble(average, {"Body": body, "Inner": inner})
    with_mesh_roles(ch, spans)
    assert [m.role for m in ch.meshes] == ["body", "accessory"]
    n_body = average.num_vertices
    parts = body_parts(ch, mapping)
    assert parts.body is not None and parts.body_count == n_body
    assert int(parts.part_vertices(parts.index("LeftHand")).max()) < n_body  # the sphere is in no part
    assert parts.faces.shape[0] == average.faces.shape[0]
    frames = 2
    motion = Motion(ch.skeleton, 30.0, ch.skeleton.rest_rotations.expand(frames, -1, -1).clone(),
                    ch.skeleton.rest_translations.expand(frames, -1, -1).clone(), "rest")  # fmt: skip
    grot, gpos = motion.global_transforms()
    posed = ch.pose_vertices(grot, gpos)
    mats = segment_matrices(ch, parts, grot, gpos)

    def sampled_sphere(sdf) -> int:  # type: ignore[no-untyped-def]
        return int((sample_pairs(sdf, posed, mats).vertex >= n_body).sum())

    sdf = body_sdf(ch, parts)
    assert sampled_sphere(sdf) == 0
    m = measure_clip(ch, mapping, sdf, motion)
    assert m.num_vertices == n_body and float(m.vertex_depth[:, n_body:].abs().max()) == 0.0
    assert summarize(m).summary.penetrating_vertices_percent == pytest.approx(0.0, abs=0.05)
    # The same sphere as body: left-hand vertices inside the torso, sampled against it.
    ch.meshes = [replace(x, role="body", reason="forced") for x in ch.meshes]
    assert sampled_sphere(body_sdf(ch, body_parts(ch, mapping))) > 0
