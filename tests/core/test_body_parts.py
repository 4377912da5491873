"""Body parts: segments through the joint mapping, vertex groups, paper 2's clusters and masks."""

from __future__ import annotations

import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.bodies import load_preset
from retarget_core.body_parts import (
    CLUSTERS,
    END_EFFECTOR_SEGMENTS,
    body_parts,
    mapping_by_name,
    segment_of_joints,
)
from retarget_core.canonical import CANONICAL_JOINTS, JointMapping
from retarget_core.character import Character
from retarget_core.skeleton import Skeleton


@pytest.fixture(scope="module")
def average():
    c = load_preset("male_average")
    m = mapping_by_name(c.skeleton.names)
    return c, m, body_parts(c, m)


def test_segments_follow_canonical_joints(average) -> None:
    c, m, parts = average
    assert parts.names == list(CANONICAL_JOINTS)
    assert [c.skeleton.names[j] for j in parts.joints] == parts.names
    assert torch.allclose(parts.weights.sum(1), torch.ones(c.num_vertices), atol=1e-5)
    assert parts.vertex_part.shape == (c.num_vertices,)
    assert parts.face_part.shape == (c.faces.shape[0],)
    assert parts.parent[parts.index("LeftHand")] == parts.index("LeftForeArm")
    assert parts.parent[parts.index("Hips")] == -1


def test_hand_group_is_the_hand(average) -> None:
    c, _, parts = average
    hand = parts.group("LeftHand")
    assert len(hand) > 100
    x = c.vertices[hand]
    # The left hand hangs at the body's left (+x), below the hips in the A pose, beyond the left forearm joint.
    wrist = c.skeleton.rest_global()[1][c.skeleton.index("LeftHand")]
    assert float(x[:, 0].min()) > 0.0
    assert float((x - wrist).norm(dim=1).max()) < 0.25
    faces = parts.group_faces("LeftHand")
    assert torch.isin(faces, hand).all()


def test_clusters_and_masks(average) -> None:
    _, _, parts = average
    members = parts.cluster_members()
    assert set(members) == set(CLUSTERS)
    names = {k: [parts.names[s] for s in v] for k, v in members.items()}
    assert names["left_arm"] == ["LeftArm", "LeftForeArm", "LeftHand"]
    assert names["head"] == ["Neck", "Head"]
    assert "LeftShoulder" in names["torso"] and "Hips" in names["torso"]
    assert names["right_leg"] == ["RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"]
    mask = parts.collision_mask()
    assert torch.equal(mask, mask.T)
    assert not mask.diagonal().any()
    i = parts.index
    assert not mask[i("LeftHand"), i("LeftForeArm")]  # adjacent
    assert not mask[i("LeftHand"), i("LeftArm")]  # same cluster
    assert not mask[i("LeftShoulder"), i("LeftArm")]  # parent/child across clusters
    assert mask[i("LeftHand"), i("Head")] and mask[i("LeftHand"), i("RightHand")] and mask[i("LeftArm"), i("Spine2")]
    paper2 = parts.collision_mask(ignore_arm_chest=True)
    assert not paper2[i("LeftArm"), i("Spine2")] and paper2[i("LeftForeArm"), i("Spine2")]
    for limb, segs in END_EFFECTOR_SEGMENTS.items():
        assert all(CLUSTERS[parts.cluster[i(s)]] == limb for s in segs)


def _finger_rig() -> tuple[Character, JointMapping]:
    """A chain Root -> Hips -> ... with a twist bone under the forearm and a finger under the hand."""
    names = ["Root", "Hips", "Spine", "LeftArm", "LeftForeArm", "LeftForeArmTwist", "LeftHand", "LeftIndex1"]
    parents = [-1, 0, 1, 2, 3, 4, 4, 6]
    trans = torch.tensor([[0, 0, 0], [0, 1, 0], [0, 0.2, 0], [0.2, 0.3, 0], [0.3, 0, 0], [0.1, 0, 0], [0.3, 0, 0], [0.1, 0, 0]], dtype=torch.float32)
    sk = Skeleton(names, parents, trans, rot.identity(len(names)))
    _, pos = sk.rest_global()
    verts = pos + torch.tensor([0.0, 0.0, 0.01])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [5, 6, 7]])
    joints = torch.arange(len(names))[:, None]
    ch = Character("rig", sk, verts, faces, joints, torch.ones(len(names), 1))
    mapping = JointMapping({"Hips": 1, "Spine": 2, "LeftArm": 3, "LeftForeArm": 4, "LeftHand": 6})
    return ch, mapping


def test_unmapped_joints_join_their_mapped_ancestor() -> None:
    ch, mapping = _finger_rig()
    seg = segment_of_joints(ch.skeleton.num_joints, ch.skeleton.parents, mapping)
    assert seg == ["Hips", "Hips", "Spine", "LeftArm", "LeftForeArm", "LeftForeArm", "LeftHand", "LeftHand"]
    parts = body_parts(ch, mapping)
    assert parts.names == ["Hips", "Spine", "LeftArm", "LeftForeArm", "LeftHand"]
    # The finger's vertex (joint 7) belongs to the hand group; the twist bone's (5) to the forearm.
    assert parts.group("LeftHand").tolist() == [6, 7]
    assert parts.group("LeftForeArm").tolist() == [4, 5]
    assert parts.parent == [-1, 0, 1, 2, 3]


def test_mapping_by_name_and_empty_mapping() -> None:
    ch, _ = _finger_rig()
    m = mapping_by_name(ch.skeleton.names)
    assert m.joints == {"Hips": 1, "Spine": 2, "LeftArm": 3, "LeftForeArm": 4, "LeftHand": 6}
    with pytest.raises(ValueError, match="maps no canonical joint"):
        body_parts(ch, JointMapping({}))
