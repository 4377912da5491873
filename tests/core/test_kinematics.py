"""Forward kinematics and skinning checked against the glTF definition on the shared characters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.character import Character
from retarget_core.io.gltf_read import read_gltf

SAMPLES = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples" / "characters"


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    a = gltf.accessors[index]
    view = gltf.bufferViews[a.bufferView]
    dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[a.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
    offset = (view.byteOffset or 0) + (a.byteOffset or 0)
    return np.frombuffer(blob, dtype, a.count * width, offset).reshape(a.count, width).astype(np.float64)


def gltf_reference_skinning(path: Path, local_rotations: dict[str, np.ndarray]) -> np.ndarray:
    """Skinned positions (V, 3) straight from the glTF spec: joint world = parent world * T * R * S,
    vertex = sum_k w_k * world_k * inverseBind_k * v, with the given node rotations replacing the file's."""
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    parent = {c: i for i, n in enumerate(g.nodes) for c in (n.children or [])}

    def world(i: int) -> np.ndarray:
        n = g.nodes[i]
        m = np.eye(4)
        q = local_rotations.get(n.name, np.array(n.rotation or [0, 0, 0, 1], dtype=np.float64))
        m[:3, :3] = _quat_to_mat(q) * np.array(n.scale or [1, 1, 1])
        m[:3, 3] = n.translation or [0, 0, 0]
        return world(parent[i]) @ m if i in parent else m

    skin = g.skins[0]
    ibm = _accessor(g, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    mats = np.stack([world(j) @ ibm[k] for k, j in enumerate(skin.joints)])
    prim = g.meshes[0].primitives[0]
    pos = _accessor(g, blob, prim.attributes.POSITION)
    joints = _accessor(g, blob, prim.attributes.JOINTS_0).astype(int)
    weights = _accessor(g, blob, prim.attributes.WEIGHTS_0)
    homo = np.concatenate([pos, np.ones((len(pos), 1))], 1)
    out = np.zeros((len(pos), 3))
    for k in range(joints.shape[1]):
        out += weights[:, k : k + 1] * np.einsum("vij,vj->vi", mats[joints[:, k]], homo)[:, :3]
    return out


@pytest.mark.parametrize("body", ["mh_male_bulky", "mh_female_skinny", "mh_neutral_tall"])
def test_skinning_matches_gltf_definition(shared_data: Path, body: str) -> None:
    path = shared_data / "characters" / f"{body}.glb"
    character = read_gltf(path).character
    assert character is not None
    sk = character.skeleton
    gen = torch.Generator().manual_seed(7)
    random_local = rot.normalize(rot.mul(sk.rest_rotations, rot.from_euler("XYZ", (torch.rand(sk.num_joints, 3, generator=gen) - 0.5) * 80)))
    names = {n: random_local[j].double().numpy() for j, n in enumerate(sk.names)}
    expected = gltf_reference_skinning(path, names)
    grot, gpos = kinematics.forward_kinematics(sk.parents, random_local, sk.rest_translations)
    posed = character.pose_vertices(grot, gpos)
    err = np.abs(posed.numpy() - expected).max()
    assert err < 1e-4, f"skinning differs from the glTF definition by {err:.2e} m"
    # The pose is far from rest: the check is not vacuous.
    assert np.abs(expected - character.vertices.numpy()).max() > 0.05


def test_fk_inverse_and_batching() -> None:
    gen = torch.Generator().manual_seed(0)
    parents = [-1, 0, 1, 1, 3]
    local_r = rot.normalize(torch.randn(6, 2, 5, 4, generator=gen))
    local_t = torch.randn(6, 2, 5, 3, generator=gen)
    grot, gpos = kinematics.forward_kinematics(parents, local_r, local_t)
    back_r, back_t = kinematics.global_to_local(parents, grot, gpos)
    assert torch.allclose(rot.normalize(local_r), back_r, atol=1e-5)
    assert torch.allclose(local_t, back_t, atol=1e-5)
    one_r, one_p = kinematics.forward_kinematics(parents, local_r[3, 1], local_t[3, 1])
    assert torch.allclose(one_p, gpos[3, 1], atol=1e-6)


def test_skinning_is_differentiable(shared_data: Path) -> None:
    character = read_gltf(shared_data / "characters" / "mh_male_skinny.glb").character
    assert character is not None
    sk = character.skeleton
    angles = torch.zeros(2, sk.num_joints, 3, requires_grad=True)
    local_r = rot.mul(sk.rest_rotations, rot.from_euler("XYZ", angles, degrees=False))
    grot, gpos = kinematics.forward_kinematics(sk.parents, local_r, sk.rest_translations)
    verts = character.pose_vertices(grot, gpos)
    verts[..., 1].mean().backward()
    assert angles.grad is not None and torch.isfinite(angles.grad).all() and angles.grad.abs().sum() > 0


def test_posing_a_vertex_subset_matches_posing_the_whole_mesh() -> None:
    """``Character.pose_vertex_subset`` (foot lock, the feet measures, placement) gives the whole mesh's posed
    positions of its vertices, across chunk boundaries."""
    sample = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples" / "characters" / "mh_female_skinny.glb"
    ch = read_gltf(sample).character
    assert ch is not None
    g = torch.Generator().manual_seed(0)
    f_n, j_n = 5, ch.skeleton.num_joints
    local = rot.normalize(torch.tensor([0.0, 0.0, 0.0, 1.0]) + 0.2 * torch.randn(f_n, j_n, 4, generator=g))
    trans = ch.skeleton.rest_translations.expand(f_n, -1, -1).clone()
    grot, gpos = kinematics.forward_kinematics(ch.skeleton.parents, local, trans)
    index = torch.tensor([0, 17, ch.num_vertices // 2, ch.num_vertices - 1])
    whole = ch.pose_vertices(grot, gpos)[:, index]
    assert torch.allclose(ch.pose_vertex_subset(index, grot, gpos, chunk=2), whole, atol=1e-5)


def _random_pose(ch: Character, f_n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """World joint transforms ``(f_n, J, 4)``, ``(f_n, J, 3)`` of a random pose of ``ch``."""
    g = torch.Generator().manual_seed(seed)
    local = rot.normalize(torch.tensor([0.0, 0.0, 0.0, 1.0]) + 0.2 * torch.randn(f_n, ch.skeleton.num_joints, 4, generator=g))
    trans = ch.skeleton.rest_translations.expand(f_n, -1, -1).clone()
    return kinematics.forward_kinematics(ch.skeleton.parents, local, trans)


def test_lowest_heights_are_the_posed_subset_lowest_per_frame() -> None:
    """``Character.lowest_heights`` (floor, placement, the feet measures) reads the lowest posed vertex of the
    subset on each frame, whatever the chunk, without holding every posed frame."""
    ch = read_gltf(SAMPLES / "mh_female_skinny.glb").character
    assert ch is not None
    grot, gpos = _random_pose(ch, 7)
    index = torch.arange(0, ch.num_vertices, 3)
    expected = ch.pose_vertex_subset(index, grot, gpos)[..., 1].amin(-1)
    for chunk in (None, 1, 3, 64):
        assert torch.equal(ch.lowest_heights(index, grot, gpos, chunk), expected)
    assert ch.lowest_heights(index, grot[:0], gpos[:0]).shape == (0,)


def test_skinning_gives_the_same_frames_in_any_chunk() -> None:
    """Skinning in chunks of frames (a memory bound) gives each frame bit for bit what it gives alone."""
    ch = read_gltf(SAMPLES / "mh_female_skinny.glb").character
    assert ch is not None
    grot, gpos = _random_pose(ch, 6, seed=1)
    rest_rot, rest_pos = ch.skeleton.rest_global()
    mats = kinematics.skinning_matrices(rest_rot, rest_pos, grot, gpos)
    weights = ch.dense_weights()
    alone = torch.stack([kinematics.linear_blend_skinning(ch.vertices, weights, mats[f : f + 1])[0] for f in range(6)])
    for chunk in (None, 1, 4):
        assert torch.equal(kinematics.linear_blend_skinning(ch.vertices, weights, mats, chunk), alone)


def test_posing_over_each_vertex_influences_equals_the_dense_form() -> None:
    """Posing without gradients (each vertex's own influences, compiled) gives the dense differentiable form's
    positions, batch dimensions kept, and any rows of it bit for bit as the whole mesh's."""
    ch = read_gltf(SAMPLES / "mh_female_skinny.glb").character
    assert ch is not None
    grot, gpos = _random_pose(ch, 6, seed=2)
    rest_rot, rest_pos = ch.skeleton.rest_global()
    mats = kinematics.skinning_matrices(rest_rot, rest_pos, grot, gpos)
    dense = kinematics.linear_blend_skinning(ch.vertices, ch.dense_weights(), mats)
    posed = ch.pose_vertices(grot, gpos)
    assert posed.dtype == dense.dtype and posed.shape == dense.shape
    assert (posed - dense).abs().max() < 1e-5 and (dense - ch.vertices).abs().max() > 0.05
    batched = ch.pose_vertices(grot.view(2, 3, *grot.shape[1:]), gpos.view(2, 3, *gpos.shape[1:]))
    assert torch.equal(batched.view_as(posed), posed)
    index = torch.tensor([ch.num_vertices - 1, 0, 5, 5])
    assert torch.equal(ch.pose_rows(index, grot, gpos), posed[:, index])
    assert torch.equal(ch.pose_vertex_subset(index, grot, gpos, chunk=4), posed[:, index])


def _joint_by_joint(parents: list[int], local_rotations: torch.Tensor, local_translations: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """The glTF recursion written out joint after joint (the reference the level-wise FK must equal)."""
    grot: list[torch.Tensor] = []
    gpos: list[torch.Tensor] = []
    for j, p in enumerate(parents):
        r, t = local_rotations[..., j, :], local_translations[..., j, :]
        grot.append(r if p < 0 else rot.mul(grot[p], r))
        gpos.append(t if p < 0 else gpos[p] + rot.apply(grot[p], t))
    return torch.stack(grot, -2), torch.stack(gpos, -2)


def test_fk_by_depth_equals_joint_by_joint() -> None:
    """Two roots, branches of different depths, a parent listed long before its children: equal bit for bit,
    with broadcast batch shapes, and the same gradients up to float rounding."""
    parents = [-1, 0, 1, 0, 3, 4, -1, 6, 2, 8, 5, 1]
    gen = torch.Generator().manual_seed(3)
    q = rot.normalize(torch.randn(2, 5, len(parents), 4, generator=gen, dtype=torch.float64))
    t = torch.randn(5, len(parents), 3, generator=gen, dtype=torch.float64)
    want = _joint_by_joint(parents, q, t.expand(2, -1, -1, -1))
    got = kinematics.forward_kinematics(parents, q, t)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    qa, qb = q.clone().requires_grad_(), q.clone().requires_grad_()
    w = torch.randn(2, 5, len(parents), 3, generator=gen, dtype=torch.float64)
    (_joint_by_joint(parents, qa, t.expand(2, -1, -1, -1))[1] * w).sum().backward()
    (kinematics.forward_kinematics(parents, qb, t)[1] * w).sum().backward()
    assert torch.allclose(qa.grad, qb.grad, rtol=1e-12, atol=1e-12)


def test_rest_pose_is_computed_once_and_handed_out_as_copies() -> None:
    from retarget_core.skeleton import Skeleton

    gen = torch.Generator().manual_seed(4)
    sk = Skeleton(["a", "b", "c"], [-1, 0, 1], torch.randn(3, 3, generator=gen),
                  rot.normalize(torch.randn(3, 4, generator=gen)))  # fmt: skip
    grot, gpos = sk.rest_global()
    assert torch.equal(gpos, kinematics.forward_kinematics(sk.parents, sk.rest_rotations, sk.rest_translations)[1])
    first = gpos.clone()
    gpos += 1.0  # a caller's copy: the next call is unaffected
    assert torch.equal(sk.rest_global()[1], first)
    sk.rest_translations[2] += 0.5  # the rest pose changed in place: computed again
    assert torch.allclose(sk.rest_global()[1][2], first[2] + rot.apply(grot[1], torch.tensor([0.5, 0.5, 0.5])))
