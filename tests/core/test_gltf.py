"""glTF / GLB reading and animated GLB writing, checked against the shared characters and the Khronos validator."""

from __future__ import annotations

import importlib.util
import json
import math
import struct
import sys
import time
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch
from scipy.spatial.transform import Rotation

from retarget_core import rotations as rot
from retarget_core.canonical import CANONICAL_JOINTS
from retarget_core.config import get_settings
from retarget_core.errors import InvalidFileError, LimitExceededError, UnsupportedFileError
from retarget_core.io.gltf_read import infer_fps, read_gltf, read_gltf_character
from retarget_core.io.gltf_write import write_glb
from retarget_core.motion import Motion

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from gltf_builders import FLOAT, UBYTE, USHORT, Builder, add_skinned_chain, patch_glb_json, trs_matrix  # noqa: E402


def _load_validator():
    spec = importlib.util.spec_from_file_location("gltf_validator", HERE.parent / "gltf_validator.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gltf_validator = _load_validator()


@pytest.fixture(scope="module")
def character_files(shared_data: Path) -> list[Path]:
    files = sorted((shared_data / "characters").glob("*.glb"))
    if not files:
        pytest.skip(f"no GLB characters in {shared_data / 'characters'}")
    return files


def _file_positions(path: Path) -> np.ndarray:
    """POSITION of the first primitive, decoded by pygltflib (independently of our accessor code)."""
    g = pygltflib.GLTF2().load(str(path))
    acc = g.accessors[g.meshes[0].primitives[0].attributes.POSITION]
    view = g.bufferViews[acc.bufferView]
    blob = g.binary_blob()
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(blob, "<f4", acc.count * 3, start).reshape(-1, 3)


def _arm_motion(skeleton, frames: int, fps: float = 30.0, joint: str = "LeftArm") -> Motion:
    """A clip that swings ``joint`` about its local Z by up to 80 degrees and moves the root forward."""
    r = skeleton.rest_rotations[None].repeat(frames, 1, 1).clone()
    t = skeleton.rest_translations[None].repeat(frames, 1, 1).clone()
    j = skeleton.index(joint)
    ang = torch.linspace(0, math.radians(80), frames)
    dq = torch.stack([torch.zeros(frames), torch.zeros(frames), torch.sin(ang / 2), torch.cos(ang / 2)], -1)
    r[:, j] = rot.mul(r[:, j], dq)
    t[:, 0, 2] += torch.linspace(0, 0.5, frames)
    return Motion(skeleton, fps, r, t, "swing")


# ----- the shared characters -----------------------------------------------------------------------------------------
def test_shared_characters_read(character_files: list[Path]) -> None:
    for path in character_files:
        contents = read_gltf(path)
        ch = contents.character
        assert ch is not None, path
        assert ch.num_vertices == 13_380 and ch.faces.shape == (26_756, 3)
        assert ch.skeleton.num_joints == 22 and set(ch.skeleton.names) == set(CANONICAL_JOINTS)
        assert ch.skeleton.names[ch.skeleton.parents.index(-1)] == "Hips"
        assert torch.allclose(ch.skin_weights.sum(1), torch.ones(ch.num_vertices), atol=1e-5)
        assert int(ch.skin_joints.max()) < 22 and int(ch.skin_joints.min()) >= 0
        assert 1.4 <= ch.height <= 2.0, (path, ch.height)
        assert ch.name == path.stem
        # Bind pose = rest pose in these files: skinning into the rest pose gives back POSITION.
        np.testing.assert_allclose(ch.vertices.numpy(), _file_positions(path), atol=1e-5)
        assert contents.motions == []


def test_shared_characters_round_trip(character_files: list[Path], tmp_path: Path) -> None:
    for path in character_files:
        ch = read_gltf_character(path)
        motion = _arm_motion(ch.skeleton, 10)
        out = tmp_path / f"{path.stem}_anim.glb"
        write_glb(ch, motion, out)
        report = gltf_validator.assert_valid_glb(out)
        assert report["info"]["animationCount"] == 1 and report["info"]["hasSkins"]
        back = read_gltf(out)
        assert back.character is not None and len(back.motions) == 1
        np.testing.assert_allclose(back.character.vertices.numpy(), ch.vertices.numpy(), atol=1e-6)
        assert torch.equal(back.character.faces, ch.faces)
        assert (
            back.character.skeleton.names == ch.skeleton.names
            and back.character.skeleton.parents == ch.skeleton.parents
        )
        np.testing.assert_allclose(
            back.character.skeleton.rest_global()[1].numpy(), ch.skeleton.rest_global()[1].numpy(), atol=1e-6
        )
        m = back.motions[0]
        assert m.fps == 30.0 and m.num_frames == 10 and m.name == "retarget"
        np.testing.assert_allclose(m.global_transforms()[1].numpy(), motion.global_transforms()[1].numpy(), atol=1e-4)
        grot_a, grot_b = m.global_transforms()[0], motion.global_transforms()[0]
        assert (rot.mul(rot.inv(grot_a), grot_b)[..., 3].abs() > 1 - 1e-6).all()


def test_static_character_is_valid(character_files: list[Path], tmp_path: Path) -> None:
    ch = read_gltf_character(character_files[0])
    out = tmp_path / "static.glb"
    write_glb(ch, None, out)
    report = gltf_validator.assert_valid_glb(out, max_warnings=0)
    assert report["info"]["animationCount"] == 0
    back = read_gltf(out)
    assert back.motions == [] and back.character is not None
    np.testing.assert_allclose(back.character.vertices.numpy(), ch.vertices.numpy(), atol=1e-6)


def test_a_300_frame_clip_round_trips(character_files: list[Path], tmp_path: Path) -> None:
    """A shared character written with a 300-frame motion reads back with every frame and the same poses."""
    ch = read_gltf_character(character_files[0])
    motion = _arm_motion(ch.skeleton, 300)
    write_glb(ch, motion, tmp_path / "long.glb")
    back = read_gltf(tmp_path / "long.glb")
    assert back.motions[0].num_frames == 300
    dot = (back.motions[0].rotations * motion.rotations).sum(-1).abs()
    assert bool((dot > 1 - 1e-5).all())  # the same rotations (q and -q alike)


# ----- writer details ------------------------------------------------------------------------------------------------
def test_written_quaternions_continuous_and_weights_normalised(character_files: list[Path], tmp_path: Path) -> None:
    ch = read_gltf_character(character_files[0])
    frames = 40
    # A full turn about Y: the canonical (w >= 0) quaternions jump sign half way; the file must not.
    r = ch.skeleton.rest_rotations[None].repeat(frames, 1, 1).clone()
    ang = torch.linspace(0, 2 * math.pi, frames)
    r[:, 0] = rot.normalize(
        torch.stack([torch.zeros(frames), torch.sin(ang / 2), torch.zeros(frames), torch.cos(ang / 2)], -1)
    )
    motion = Motion(ch.skeleton, 24.0, r, ch.skeleton.rest_translations[None].repeat(frames, 1, 1), "turn")
    # Skewed weights that do not sum to one in float32 unless the writer renormalises.
    ch.skin_weights = ch.skin_weights * 1.3 + 1e-3
    out = tmp_path / "turn.glb"
    write_glb(ch, motion, out, clip_name="turn")
    gltf_validator.assert_valid_glb(out, max_warnings=0)
    g = pygltflib.GLTF2().load(str(out))
    blob = g.binary_blob()
    anim = g.animations[0]
    assert anim.name == "turn"

    def read(acc_index: int, width: int) -> np.ndarray:
        acc = g.accessors[acc_index]
        return np.frombuffer(blob, "<f4", acc.count * width, g.bufferViews[acc.bufferView].byteOffset).reshape(
            acc.count, width
        )

    root_rot = next(
        anim.samplers[c.sampler] for c in anim.channels if c.target.node == 0 and c.target.path == "rotation"
    )
    q = read(root_rot.output, 4)
    assert ((q[1:] * q[:-1]).sum(1) > 0).all()
    times = read(root_rot.input, 1)[:, 0]
    np.testing.assert_allclose(times, np.arange(frames) / 24.0, atol=1e-6)
    assert g.accessors[root_rot.input].min == [0.0] and g.accessors[root_rot.input].max[0] == pytest.approx(
        (frames - 1) / 24.0
    )
    w = read(g.meshes[0].primitives[0].attributes.WEIGHTS_0, 4)
    assert np.abs(w.sum(1, dtype=np.float32) - 1).max() <= 1.2e-7
    # Only the root has a translation channel: the other joints keep their rest offsets.
    assert {c.target.node for c in anim.channels if c.target.path == "translation"} == {0}
    # The mesh node is a scene root, beside the skeleton root.
    mesh_node = next(i for i, n in enumerate(g.nodes) if n.mesh is not None)
    assert mesh_node in g.scenes[0].nodes and all(mesh_node not in n.children for n in g.nodes)


def test_writer_texture_and_uvs(tmp_path: Path) -> None:
    png = (
        b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x01\x00\x00\x00\x01\x08\x02\x00\x00\x00\x90wS\xde"
        b"\x00\x00\x00\x0cIDATx\x9cc\xf8\xcf\xc0\x00\x00\x03\x01\x01\x00\xc9\xfe\x92\xef\x00\x00\x00\x00IEND\xaeB`\x82"
    )
    b = Builder()
    add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    src = b.save_glb(tmp_path / "chain.glb")
    ch = read_gltf_character(src)
    assert ch.uvs is None
    ch.uvs = torch.rand(ch.num_vertices, 2)
    ch.material.image_bytes, ch.material.base_color = png, (0.5, 0.25, 1.0, 1.0)
    out = tmp_path / "textured.glb"
    write_glb(ch, None, out)
    report = gltf_validator.assert_valid_glb(out, max_warnings=0)
    assert report["info"]["hasTextures"]
    back = read_gltf_character(out)
    assert back.material.image_bytes == png and back.material.image_mime == "image/png"
    assert back.material.base_color == pytest.approx((0.5, 0.25, 1.0, 1.0))
    np.testing.assert_allclose(back.uvs.numpy(), ch.uvs.numpy(), atol=1e-7)


# ----- constructed cases ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("as_matrix", [False, True])
def test_armature_scaled_and_z_up_is_baked(tmp_path: Path, as_matrix: bool) -> None:
    """An Armature node with scale 0.01 and -90 degrees about X (a Z-up file in centimetres, bound in armature
    space) reads as metres, Y up; the same with the Armature given as a matrix."""
    b = Builder()
    q_arm = Rotation.from_euler("x", -90, degrees=True).as_quat()
    if as_matrix:
        arm = b.node("Armature", matrix=trs_matrix(q=q_arm, s=[0.01] * 3).T.reshape(-1))
    else:
        arm = b.node("Armature", rotation=q_arm, scale=[0.01, 0.01, 0.01])
    joints, tube, _ = add_skinned_chain(
        b, ["Hips", "Spine", "Head"], [(0, 0, 100), (0, 0, 40), (0, 0, 30)], parent=arm, radius=10
    )
    # Animation: Spine bends 90 degrees about X over 1 s; the armature itself is not animated.
    q_bend = Rotation.from_euler("x", [[0], [90]], degrees=True).as_quat()
    b.animation("bend", [(joints[1], "rotation", np.array([0.0, 1.0]), q_bend, "LINEAR")])
    contents = read_gltf(b.save_glb(tmp_path / "zup.glb"))
    ch = contents.character
    assert ch.skeleton.names == ["Hips", "Spine", "Head"]  # the Armature is not needed to make a tree
    _, gpos = ch.skeleton.rest_global()
    np.testing.assert_allclose(gpos.numpy(), [[0, 1.0, 0], [0, 1.4, 0], [0, 1.7, 0]], atol=1e-6)
    a = trs_matrix(q=q_arm, s=[0.01] * 3)
    np.testing.assert_allclose(ch.vertices.numpy(), tube.positions @ a[:3, :3].T, atol=1e-6)
    assert ch.height == pytest.approx(0.7, abs=1e-5)
    # World rotations are the armature's rotation; local rest rotations reproduce them without scale.
    grot, _ = ch.skeleton.rest_global()
    np.testing.assert_allclose(np.abs((grot.numpy() * q_arm).sum(-1)), 1.0, atol=1e-6)
    m = contents.motions[0]
    assert m.name == "bend" and m.skeleton is ch.skeleton
    assert m.fps == 30.0 and m.num_frames == 31  # steps of 1 s are no common rate: the default 30 fps
    _, mpos = m.global_transforms()
    # Spine bends +90 degrees about armature X: Head moves from +Z (armature) to -Y (armature) = +Z world... check:
    head_arm = np.array([0, 0, 140.0]) + Rotation.from_euler("x", 90, degrees=True).apply([0, 0, 30.0])
    expected = a[:3, :3] @ head_arm
    np.testing.assert_allclose(mpos[-1, 2].numpy(), expected, atol=1e-5)
    np.testing.assert_allclose(mpos[0].numpy(), gpos.numpy(), atol=1e-6)
    half = Rotation.from_euler("x", 45, degrees=True).apply([0, 0, 30.0])
    np.testing.assert_allclose(mpos[15, 2].numpy(), a[:3, :3] @ (np.array([0, 0, 140.0]) + half), atol=1e-5)
    # What we write back is valid and reads back the same (now in metres, Y up, without the Armature).
    out = tmp_path / "zup_out.glb"
    write_glb(ch, m, out)
    gltf_validator.assert_valid_glb(out, max_warnings=0)
    back = read_gltf(out)
    np.testing.assert_allclose(back.character.vertices.numpy(), ch.vertices.numpy(), atol=1e-6)
    np.testing.assert_allclose(back.motions[0].global_transforms()[1].numpy(), mpos.numpy(), atol=1e-5)


def test_animated_armature_helpers_and_rigid_attachments(tmp_path: Path) -> None:
    """A non-joint node between two joints joins the skeleton; an animated non-joint ancestor moves the joints;
    an unskinned mesh under a joint follows it rigidly; non-uniform scale is noted."""
    b = Builder()
    arm = b.node("Armature")
    hips = b.node("Hips", parent=arm, translation=[0, 1, 0])
    helper = b.node(
        None, parent=hips, translation=[0, 0.1, 0], rotation=Rotation.from_euler("y", 90, degrees=True).as_quat()
    )
    head = b.node("Hips", parent=helper, translation=[0, 0.5, 0], scale=[1, 2, 1])  # duplicate name
    world = np.stack([trs_matrix((0, 1, 0)), trs_matrix((0, 1.6, 0))])
    tube_pos = np.array([[0.1, 1.0, 0], [-0.1, 1.0, 0], [0, 1.6, 0.1]], np.float32)
    mesh = b.mesh([{
        "attributes": {
            "POSITION": b.accessor(tube_pos),
            "JOINTS_0": b.accessor(np.array([[0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]), UBYTE, kind="VEC4"),
            "WEIGHTS_0": b.accessor(np.array([[1.0, 0, 0, 0]] * 3), kind="VEC4"),
        },
    }])  # fmt: skip
    b.node("Body", mesh=mesh, skin=b.skin([hips, head], np.linalg.inv(world)))
    hat = b.mesh(
        [{"attributes": {"POSITION": b.accessor(np.array([[0, 0.2, 0], [0.1, 0.2, 0], [0, 0.3, 0]], np.float32))}}]
    )
    b.node("Hat", parent=head, mesh=hat)
    b.animation("lift", [(arm, "translation", np.array([0.0, 1.0]), np.array([[0, 0, 0], [0, 2, 0]]), "LINEAR")])
    contents = read_gltf(b.save_glb(tmp_path / "helpers.glb"))
    ch = contents.character
    assert ch.skeleton.names == ["Hips", f"joint_{helper}", "Hips_2"]
    assert ch.skeleton.parents == [-1, 0, 1]
    assert any("non-uniform scale" in n for n in contents.notes)
    _, gpos = ch.skeleton.rest_global()
    np.testing.assert_allclose(gpos.numpy(), [[0, 1, 0], [0, 1.1, 0], [0, 1.6, 0]], atol=1e-6)
    assert ch.num_vertices == 6 and ch.faces.shape == (2, 3)
    # The hat: its node's world matrix (scale 2 in Y under a 90 degree Y turn) applied, bound to joint 2 alone.
    # Meshes merge in node order: the hat (under the Armature) comes before the body (a later scene root).
    np.testing.assert_allclose(ch.vertices[:3].numpy(), [[0, 2.0, 0], [0, 2.0, -0.1], [0, 2.2, 0]], atol=1e-6)
    assert (ch.skin_joints[:3, 0] == 2).all() and (ch.skin_weights[:3, 0] == 1).all()
    # The body's third vertex was bound to Head with an unrotated bind matrix; the rest pose turns Head by 90
    # degrees about Y (and scales Y by 2): v = W_head(rest) * IBM * v_bind moves it from +Z to +X.
    np.testing.assert_allclose(ch.vertices[3:].numpy(), [[0.1, 1, 0], [-0.1, 1, 0], [0.1, 1.6, 0]], atol=1e-6)
    (m,) = contents.motions
    np.testing.assert_allclose(m.global_transforms()[1][-1].numpy(), gpos.numpy() + [0, 2, 0], atol=1e-6)


def test_two_skins_and_primitives_merge(tmp_path: Path) -> None:
    b = Builder()
    joints, tube, mesh_node = add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    # A second primitive on the same mesh (a triangle fan around Head) and a second mesh node with its own skin
    # listing the joints in another order (Head, Hips), with JOINTS as UNSIGNED_BYTE and an indexless strip.
    fan = np.array([[0, 1.8, 0], [0.1, 1.8, 0], [0.1, 1.9, 0], [0, 1.95, 0], [-0.1, 1.9, 0]], np.float32)
    prim2 = {
        "attributes": {
            "POSITION": b.accessor(fan),
            "JOINTS_0": b.accessor(np.tile([2, 0, 0, 0], (5, 1)), UBYTE, kind="VEC4"),
            "WEIGHTS_0": b.accessor(np.tile([1.0, 0, 0, 0], (5, 1)), kind="VEC4"),
            "TEXCOORD_0": b.accessor(np.full((5, 2), 0.5, np.float32)),
        },
        "mode": 6,
    }
    b.gltf.meshes[0].primitives.append(
        pygltflib.Primitive(attributes=pygltflib.Attributes(**prim2["attributes"]), mode=6)
    )
    strip = np.array([[0.2, 0, 0], [0.3, 0, 0], [0.2, 0.1, 0], [0.3, 0.1, 0]], np.float32)
    world = np.stack([trs_matrix((0, 1.8, 0)), trs_matrix((0, 1.0, 0))])
    mesh2 = b.mesh([{
        "attributes": {
            "POSITION": b.accessor(strip),
            "JOINTS_0": b.accessor(np.tile([1, 0, 0, 0], (4, 1)), UBYTE, kind="VEC4"),
            "WEIGHTS_0": b.accessor(np.tile([1.0, 0, 0, 0], (4, 1)), kind="VEC4"),
        },
        "mode": 5,
    }])  # fmt: skip
    skin2 = b.skin([joints[2], joints[0]], np.linalg.inv(world))
    b.node("Shoe", mesh=mesh2, skin=skin2)
    contents = read_gltf(b.save_glb(tmp_path / "merge.glb"))
    ch = contents.character
    assert "2 skins merged into one skeleton (union of their joints)" in contents.notes
    n1 = len(tube.positions)
    assert ch.num_vertices == n1 + 5 + 4
    assert ch.faces.shape[0] == len(tube.faces) + 3 + 2
    np.testing.assert_array_equal(
        ch.faces[len(tube.faces) : len(tube.faces) + 3].numpy(), n1 + np.array([[1, 2, 0], [2, 3, 0], [3, 4, 0]])
    )
    np.testing.assert_array_equal(ch.faces[-2:].numpy(), n1 + 5 + np.array([[0, 1, 2], [1, 3, 2]]))
    head, hips = ch.skeleton.index("Head"), ch.skeleton.index("Hips")
    assert (ch.skin_joints[n1 : n1 + 5, 0] == head).all() and (ch.skin_joints[n1 + 5 :, 0] == hips).all()
    np.testing.assert_allclose(ch.vertices[n1:].numpy(), np.concatenate([fan, strip]), atol=1e-6)
    # UVs: present on one primitive only; the others get zeros.
    assert ch.uvs is not None and ch.uvs.shape == (ch.num_vertices, 2)
    assert (ch.uvs[n1 : n1 + 5] == 0.5).all() and (ch.uvs[:n1] == 0).all()


def test_normalized_weights_strided_positions_and_eight_influences(tmp_path: Path) -> None:
    b = Builder()
    joints, tube, _ = add_skinned_chain(
        b,
        ["A", "B", "C", "D", "E"],
        [(0, 1, 0), (0, 0.2, 0), (0, 0.2, 0), (0, 0.2, 0), (0, 0.2, 0)],
        weight_component=USHORT,
        joint_component=UBYTE,
    )
    ch = read_gltf_character(b.save_glb(tmp_path / "ushort.glb"))
    np.testing.assert_allclose(ch.skin_weights.sum(1).numpy(), 1.0, atol=1e-6)
    dense = ch.dense_weights().numpy()
    expected = np.zeros_like(dense)
    np.add.at(expected, (np.arange(len(tube.joints))[:, None], tube.joints), tube.weights)
    np.testing.assert_allclose(dense, expected, atol=1e-4)

    # Eight influences (JOINTS_1/WEIGHTS_1) reduce to the four largest, renormalised; POSITION with a byteStride.
    b = Builder()
    joints, tube, mesh_node = add_skinned_chain(b, ["A", "B", "C", "D", "E"], [(0, 1, 0)] + [(0, 0.2, 0)] * 4)
    n = len(tube.positions)
    j8 = np.tile([0, 1, 2, 3, 4, 0, 0, 0], (n, 1))
    w8 = np.tile([0.05, 0.3, 0.1, 0.2, 0.25, 0.1, 0.0, 0.0], (n, 1))  # joint 0 twice: 0.15 in all
    attrs = b.gltf.meshes[0].primitives[0].attributes
    attrs.POSITION = b.accessor(tube.positions.astype(np.float32), stride=20)
    attrs.JOINTS_0 = b.accessor(j8[:, :4], USHORT, kind="VEC4")
    attrs.WEIGHTS_0 = b.accessor(w8[:, :4], kind="VEC4")
    attrs.JOINTS_1 = b.accessor(j8[:, 4:], USHORT, kind="VEC4")
    attrs.WEIGHTS_1 = b.accessor(w8[:, 4:], kind="VEC4")
    ch = read_gltf_character(b.save_glb(tmp_path / "eight.glb"))
    np.testing.assert_array_equal(ch.skin_joints[0].numpy(), [1, 4, 3, 0])
    np.testing.assert_allclose(ch.skin_weights[0].numpy(), np.array([0.3, 0.25, 0.2, 0.15]) / 0.9, atol=1e-6)
    # All eight influences are used to skin the bind pose into the rest pose (identical here).
    np.testing.assert_allclose(ch.vertices.numpy(), tube.positions, atol=1e-6)


def test_sparse_accessor_and_embedded_gltf(tmp_path: Path) -> None:
    b = Builder()
    joints, tube, _ = add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    n = len(tube.positions)
    moved = tube.positions.copy()
    moved[[2, 7]] += [0.0, 0.0, 0.05]
    attrs = b.gltf.meshes[0].primitives[0].attributes
    attrs.POSITION = b.sparse_accessor(tube.positions, n, np.array([2, 7]), moved[[2, 7]], "VEC3")
    # An animation whose translation output is a sparse accessor without a bufferView (zeros + two keys).
    times = np.array([0.0, 0.5, 1.0])
    out = b.sparse_accessor(None, 3, np.array([1, 2]), np.array([[0, 1.1, 0], [0, 1.2, 0]]), "VEC3")
    b.gltf.animations.append(
        pygltflib.Animation(
            samplers=[
                pygltflib.AnimationSampler(input=b.accessor(times.astype(np.float32)), output=out, interpolation="STEP")
            ],
            channels=[
                pygltflib.AnimationChannel(
                    sampler=0, target=pygltflib.AnimationChannelTarget(node=joints[0], path="translation")
                )
            ],
        )
    )
    path = b.save_gltf_embedded(tmp_path / "embedded.gltf")
    assert json.loads(path.read_text())["buffers"][0]["uri"].startswith("data:")
    contents = read_gltf(path, fps=10)
    np.testing.assert_allclose(contents.character.vertices.numpy(), moved, atol=1e-6)
    m = contents.motions[0]
    assert m.name == "animation_0" and m.fps == 10 and m.num_frames == 11
    root_y = m.global_transforms()[1][:, 0, 1].numpy()
    np.testing.assert_allclose(root_y, [0.0] * 5 + [1.1] * 5 + [1.2], atol=1e-6)


def test_interpolations_and_fps_inference(tmp_path: Path) -> None:
    b = Builder()
    root = b.node("Root")
    arm = b.node("Arm", parent=root, translation=[1, 0, 0])
    times = np.arange(0, 25) / 24.0  # 1 s at 24 fps
    angles = np.linspace(0, 120, 25)
    q = Rotation.from_euler("z", angles[:, None], degrees=True).as_quat()
    q[1::2] *= -1  # alternate signs: the same rotations, slerp must take the short way
    b.animation("lin", [(arm, "rotation", times, q, "LINEAR")])
    # CUBICSPLINE: translation x(t) = t^2 via Hermite keys at 0, 1 (values 0, 1; tangents dx/dt = 0, 2).
    cub = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [2, 0, 0], [1, 0, 0], [0, 0, 0]], np.float32)
    b.animation(None, [(root, "translation", np.array([0.0, 1.0]), cub, "CUBICSPLINE")])
    contents = read_gltf(b.save_glb(tmp_path / "interp.glb"))
    assert contents.character is None
    assert any("no skin" in note for note in contents.notes) is False  # no meshes: nothing to complain about
    lin, cubic = contents.motions
    assert lin.skeleton.names == ["Root", "Arm"] and lin.fps == 24.0 and lin.num_frames == 25
    got = Rotation.from_quat(lin.global_transforms()[0][:, 1].numpy()).as_euler("xyz", degrees=True)[:, 2]
    np.testing.assert_allclose(got, angles, atol=1e-3)
    assert cubic.name == "animation_1" and cubic.fps == 30.0 and cubic.num_frames == 31
    x = cubic.global_transforms()[1][:, 0, 0].numpy()
    np.testing.assert_allclose(x, (np.arange(31) / 30.0) ** 2, atol=1e-5)
    # Resampling at an explicit rate: frame count = floor(duration * fps) + 1.
    assert read_gltf(tmp_path / "interp.glb", fps=50).motions[0].num_frames == 51


def test_writer_large_indices_and_many_joints(tmp_path: Path) -> None:
    """Over 255 joints: UNSIGNED_SHORT joints; over 65535 vertices: UNSIGNED_INT indices; odd weights."""
    from retarget_core.character import Character
    from retarget_core.skeleton import Skeleton

    n_joints, n_rings, ring = 300, 12_000, 6
    skel = Skeleton(
        [f"bone{j}" for j in range(n_joints)], list(range(-1, n_joints - 1)),
        torch.tensor([[0.0, 0.01, 0.0]] * n_joints), rot.identity(n_joints),
    )  # fmt: skip
    ang = torch.arange(ring) * (2 * math.pi / ring)
    y = torch.linspace(0.01, 0.01 * n_joints, n_rings)
    verts = torch.stack(
        [
            0.05 * torch.cos(ang)[None].expand(n_rings, ring),
            y[:, None].expand(n_rings, ring),
            0.05 * torch.sin(ang)[None].expand(n_rings, ring),
        ],
        -1,
    ).reshape(-1, 3)
    k = torch.arange(n_rings - 1)[:, None] * ring + torch.arange(ring)[None]
    k1 = (k + 1) - ring * ((k + 1) % ring == 0).long()
    faces = torch.cat([torch.stack([k, k1, k1 + ring], -1), torch.stack([k, k1 + ring, k + ring], -1)]).reshape(-1, 3)
    bone = (y / 0.01).long().clamp(0, n_joints - 1)[:, None].expand(n_rings, ring).reshape(-1)
    joints = torch.stack([bone, (bone - 1).clamp_min(0), torch.zeros_like(bone)], -1)
    weights = torch.tensor([0.7, 0.3, 0.0]).expand(len(bone), 3) * torch.rand(len(bone), 1).add(0.5)
    ch = Character("tall", skel, verts, faces, joints, weights)
    assert ch.num_vertices > 65535
    motion = _arm_motion(skel, 3, joint="bone150")
    out = tmp_path / "tall.glb"
    write_glb(ch, motion, out)
    gltf_validator.assert_valid_glb(out, max_warnings=0)
    g = pygltflib.GLTF2().load(str(out))
    prim = g.meshes[0].primitives[0]
    assert (
        g.accessors[prim.indices].componentType == 5125 and g.accessors[prim.attributes.JOINTS_0].componentType == 5123
    )
    back = read_gltf(out)
    np.testing.assert_allclose(back.character.vertices.numpy(), verts.numpy(), atol=1e-5)  # 300 float32 FK steps
    np.testing.assert_allclose(back.character.skin_weights[:, :2].numpy(), [[0.7, 0.3]] * len(bone), atol=1e-6)
    np.testing.assert_allclose(
        back.motions[0].global_transforms()[1].numpy(), motion.global_transforms()[1].numpy(), atol=1e-4
    )


def test_infer_fps_rounding() -> None:
    from retarget_core.io.gltf_read import _Channel

    def chans(step: float) -> list:
        return [_Channel(0, "translation", np.arange(10) * step, np.zeros((10, 3)), "LINEAR")]

    assert infer_fps(chans(1 / 59.94), 30.0) == 60.0
    assert infer_fps(chans(1 / 25), 30.0) == 25.0
    assert infer_fps(chans(1 / 119.0), 30.0) == 120.0
    assert infer_fps(chans(0.5), 30.0) == 30.0
    assert infer_fps(chans(1 / 37.0), 30.0) == 30.0


def test_unskinned_files(tmp_path: Path) -> None:
    b = Builder()
    mesh = b.mesh([{"attributes": {"POSITION": b.accessor(np.eye(3, dtype=np.float32))}}])
    b.node("Box", mesh=mesh)
    path = b.save_glb(tmp_path / "static_mesh.glb")
    contents = read_gltf(path)
    assert contents.character is None and contents.motions == []
    assert any("no skin" in n for n in contents.notes)
    with pytest.raises(InvalidFileError, match="has no skin: a target character must be a skinned mesh"):
        read_gltf_character(path)
    # Animated node hierarchy without skin: the animated node, its ancestors and descendants.
    b = Builder()
    top = b.node("Top")
    mid = b.node("Mid", parent=top, translation=[0, 1, 0])
    b.node("Leaf", parent=mid, translation=[0, 1, 0])
    b.node("Other")
    b.node("BoxNode", parent=mid, mesh=b.mesh([{"attributes": {"POSITION": b.accessor(np.eye(3, dtype=np.float32))}}]))
    b.animation(
        "spin",
        [
            (
                mid,
                "rotation",
                np.array([0.0, 1.0]),
                Rotation.from_euler("x", [[0], [90]], degrees=True).as_quat(),
                "LINEAR",
            )
        ],
    )
    contents = read_gltf(b.save_glb(tmp_path / "hier.glb"))
    assert contents.character is None
    (m,) = contents.motions
    assert m.skeleton.names == ["Top", "Mid", "Leaf", "BoxNode"]
    np.testing.assert_allclose(m.global_transforms()[1][-1, 2].numpy(), [0, 1, 1], atol=1e-5)


# ----- hostile files -------------------------------------------------------------------------------------------------
def _valid_glb(tmp_path: Path) -> tuple[Builder, Path]:
    b = Builder()
    add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    return b, b.save_glb(tmp_path / "ok.glb")


def _raises_fast(path: Path, match: str, error: type[Exception] = InvalidFileError) -> None:
    t0 = time.perf_counter()
    with pytest.raises(error, match=match):
        read_gltf(path)
    # A generous bound (shared machines are noisy): hostile counts must never be allocated or looped over.
    assert time.perf_counter() - t0 < 10.0


def test_external_uris_rejected(tmp_path: Path) -> None:
    b, _ = _valid_glb(tmp_path)
    (tmp_path / "model.bin").write_bytes(b"\0" * 4096)  # present, and still never opened
    doc = json.loads(b.gltf.to_json())
    doc["buffers"] = [{"uri": "model.bin", "byteLength": 4096}]
    (tmp_path / "ext.gltf").write_text(json.dumps(doc))
    _raises_fast(tmp_path / "ext.gltf", "external resource 'model.bin'")
    b, _ = _valid_glb(tmp_path)
    b.gltf.images.append(pygltflib.Image(uri="../secret/texture.png"))
    _raises_fast(b.save_glb(tmp_path / "img.glb"), r"external resource '\.\./secret/texture\.png'")
    b, _ = _valid_glb(tmp_path)
    b.gltf.images.append(pygltflib.Image(uri="file:///etc/passwd"))
    _raises_fast(b.save_glb(tmp_path / "img2.glb"), "file:///etc/passwd")


def test_broken_containers(tmp_path: Path) -> None:
    _, ok = _valid_glb(tmp_path)
    raw = ok.read_bytes()
    (tmp_path / "trunc.glb").write_bytes(raw[: len(raw) - 100])
    _raises_fast(tmp_path / "trunc.glb", "truncated")
    (tmp_path / "trunc2.glb").write_bytes(raw[:10])
    _raises_fast(tmp_path / "trunc2.glb", "truncated")
    (tmp_path / "magic.glb").write_bytes(b"glTX" + raw[4:])
    _raises_fast(tmp_path / "magic.glb", "not a glTF file")
    (tmp_path / "v1.glb").write_bytes(raw[:4] + struct.pack("<I", 1) + raw[8:])
    _raises_fast(tmp_path / "v1.glb", "version 1", UnsupportedFileError)
    (tmp_path / "bad.gltf").write_text('{"asset": {"version": "2.0"}, "nodes": [')
    _raises_fast(tmp_path / "bad.gltf", "cannot be parsed")
    (tmp_path / "v1.gltf").write_text('{"asset": {"version": "1.0"}}')
    _raises_fast(tmp_path / "v1.gltf", "only glTF 2.0", UnsupportedFileError)
    (tmp_path / "draco.gltf").write_text(
        '{"asset": {"version": "2.0"}, "extensionsRequired": ["KHR_draco_mesh_compression"]}'
    )
    _raises_fast(tmp_path / "draco.gltf", "KHR_draco_mesh_compression", UnsupportedFileError)


def test_hostile_accessors(tmp_path: Path) -> None:
    b, _ = _valid_glb(tmp_path)
    b.gltf.accessors[0].count = 10**12  # POSITION: the vertex limit comes first
    _raises_fast(b.save_glb(tmp_path / "huge.glb"), "max_vertices", LimitExceededError)
    b, _ = _valid_glb(tmp_path)
    b.gltf.accessors[b.gltf.skins[0].inverseBindMatrices].count = 10**12
    _raises_fast(b.save_glb(tmp_path / "huge_ibm.glb"), "max_accessor_elements", LimitExceededError)
    b, _ = _valid_glb(tmp_path)
    b.gltf.accessors[b.gltf.meshes[0].primitives[0].indices].count = 10**12
    _raises_fast(b.save_glb(tmp_path / "huge_idx.glb"), "max_triangles", LimitExceededError)
    b, _ = _valid_glb(tmp_path)
    b.gltf.accessors[0].count = 1_000_000  # under the element limit, far past the buffer
    _raises_fast(b.save_glb(tmp_path / "past.glb"), "bufferView has")
    b, _ = _valid_glb(tmp_path)
    b.gltf.accessors[0].byteOffset = 2**40
    _raises_fast(b.save_glb(tmp_path / "offset.glb"), "bufferView has")
    b, _ = _valid_glb(tmp_path)
    b.gltf.bufferViews[0].byteLength = 10**9
    _raises_fast(b.save_glb(tmp_path / "view.glb"), "runs past the end of buffers")
    b, _ = _valid_glb(tmp_path)
    b.gltf.accessors[0].componentType = 5124
    _raises_fast(b.save_glb(tmp_path / "ctype.glb"), "componentType")
    b, _ = _valid_glb(tmp_path)
    b.gltf.nodes[0].children.append(0)
    _raises_fast(b.save_glb(tmp_path / "cycle.glb"), "more than one parent|cycle")
    b, _ = _valid_glb(tmp_path)
    b.gltf.nodes[2].children.append(0)  # Head -> Hips: a loop with no root
    b.gltf.scenes[0].nodes.remove(0)
    _raises_fast(b.save_glb(tmp_path / "loop.glb"), "cycle")
    _, ok = _valid_glb(tmp_path)
    for old, new, match in [
        ('"count":', '"count":"12","x":', r"count = '12' must be an integer"),
        ('"mesh":0', '"mesh":7', r"nodes\[3\]\.mesh = 7 is not a valid index"),
        ('"joints":[', '"joints":[true,', "skins\\[0\\]\\.joints = True is not a valid index"),
        ('"nodes":[', '"nodes":{"a":1},"x":[', "'nodes' must be an array"),
    ]:
        (tmp_path / "types.glb").write_bytes(patch_glb_json(ok.read_bytes(), old, new))
        _raises_fast(tmp_path / "types.glb", match)


def test_out_of_range_indices_and_nan(tmp_path: Path) -> None:
    b = Builder()
    _, tube, _ = add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    faces = tube.faces.copy()
    faces[3, 1] = 10_000
    b.gltf.meshes[0].primitives[0].indices = b.accessor(faces.reshape(-1), 5125)
    _raises_fast(b.save_glb(tmp_path / "index.glb"), "index 10000, out of range")

    b = Builder()
    _, tube, _ = add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    pos = tube.positions.astype(np.float32)
    pos[5, 1] = np.nan
    b.gltf.meshes[0].primitives[0].attributes.POSITION = b.accessor(pos)
    _raises_fast(b.save_glb(tmp_path / "nan.glb"), "POSITION contains NaN")

    b = Builder()
    _, tube, _ = add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    j = tube.joints.copy()
    j[0, 0] = 9
    b.gltf.meshes[0].primitives[0].attributes.JOINTS_0 = b.accessor(j, USHORT, kind="VEC4")
    _raises_fast(b.save_glb(tmp_path / "joint.glb"), "the skin has 3 joints")

    b = Builder()
    add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    b.gltf.nodes[1].translation = [0.0, 12345.5, 0.0]
    (tmp_path / "inf.glb").write_bytes(patch_glb_json(b.glb_bytes(), "12345.5", "1e400"))  # parses as infinity
    _raises_fast(tmp_path / "inf.glb", r"nodes\[1\]\.translation contains NaN or infinite")

    b = Builder()
    add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    ibm = b.gltf.skins[0].inverseBindMatrices
    b.gltf.skins[0].inverseBindMatrices = b.accessor(np.full((3, 4, 4), np.nan, np.float32), FLOAT, kind="MAT4")
    assert ibm is not None
    _raises_fast(b.save_glb(tmp_path / "ibm.glb"), "inverseBindMatrices contains NaN")


def test_limits_from_settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _, ok = _valid_glb(tmp_path)
    for env, match in [
        ("RETARGET_MAX_FILE_BYTES", "max_file_bytes"),
        ("RETARGET_MAX_VERTICES", "max_vertices"),
        ("RETARGET_MAX_JOINTS", "max_joints"),
        ("RETARGET_MAX_TRIANGLES", "max_triangles"),
    ]:
        with monkeypatch.context() as mp:
            mp.setenv(env, "2")
            get_settings.cache_clear()
            try:
                _raises_fast(ok, match, LimitExceededError)
            finally:
                get_settings.cache_clear()
    b = Builder()
    joints, _, _ = add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    b.animation("long", [(joints[0], "translation", np.array([0.0, 1e6]), np.zeros((2, 3)), "LINEAR")])
    _raises_fast(b.save_glb(tmp_path / "long.glb"), "max_frames", LimitExceededError)


def test_writer_rejects_bad_input_and_maps_motion_by_name(tmp_path: Path) -> None:
    b = Builder()
    add_skinned_chain(b, ["Hips", "Spine", "Head"], [(0, 1, 0), (0, 0.4, 0), (0, 0.4, 0)])
    ch = read_gltf_character(b.save_glb(tmp_path / "chain.glb"))
    # A motion on a subset skeleton (Hips, Head): Spine keeps its rest transform.
    sub = ch.skeleton.subset([0, 2])
    motion = _arm_motion(sub, 5, joint="Head")
    out = tmp_path / "subset.glb"
    write_glb(ch, motion, out)
    gltf_validator.assert_valid_glb(out, max_warnings=0)
    m = read_gltf(out).motions[0]
    np.testing.assert_allclose(
        m.rotations[:, 1].numpy(), ch.skeleton.rest_rotations[1][None].expand(5, 4).numpy(), atol=1e-6
    )
    np.testing.assert_allclose(m.rotations[:, 0].numpy(), motion.rotations[:, 0].numpy(), atol=1e-6)
    other = Motion(
        type(sub)(["Foo"], [-1], torch.zeros(1, 3), rot.identity(1)), 30.0, rot.identity(2, 1), torch.zeros(2, 1, 3)
    )
    with pytest.raises(ValueError, match="animates none of the joints"):
        write_glb(ch, other, tmp_path / "x.glb")
    ch.vertices[0, 0] = float("nan")
    with pytest.raises(ValueError, match="vertices contain NaN"):
        write_glb(ch, None, tmp_path / "x.glb")
    ch.vertices[0, 0] = 0.0
    ch.faces[0, 0] = ch.num_vertices
    with pytest.raises(ValueError, match="faces refer to vertices outside"):
        write_glb(ch, None, tmp_path / "x.glb")


def test_json_chunk_padded_with_nul_and_bad_fps(tmp_path: Path) -> None:
    _, ok = _valid_glb(tmp_path)
    raw = ok.read_bytes()
    json_len = struct.unpack_from("<I", raw, 12)[0]
    text = raw[20 : 20 + json_len].rstrip(b" ") + b"\0" * 8
    text += b"\0" * (-len(text) % 4)
    rest = raw[20 + json_len :]
    padded = b"glTF" + struct.pack("<III", 2, 20 + len(text) + len(rest), len(text)) + b"JSON" + text + rest
    (tmp_path / "nul.glb").write_bytes(padded)
    assert read_gltf(tmp_path / "nul.glb").character.num_vertices == read_gltf(ok).character.num_vertices
    with pytest.raises(ValueError, match="fps must be a positive number"):
        read_gltf(ok, fps=0)
