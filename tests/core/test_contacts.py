"""Contact detection (hands, feet), triangle intersection and vertex correspondence on constructed cases."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from retarget_core import kinematics
from retarget_core.bodies import load_preset
from retarget_core.body_parts import body_parts, mapping_by_name
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import build_correspondence, transfer_contacts
from retarget_core.contacts.foot_contact import FootContactParams, detect_foot_contacts, fill_window
from retarget_core.contacts.self_contact import detect_self_contacts
from retarget_core.contacts.triangles import intersecting_pairs, triangles_intersect

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest_contacts import box_pose, hand_on_hip_pose, two_boxes  # noqa: E402


@pytest.fixture(scope="module")
def average():
    c = load_preset("male_average")
    m = mapping_by_name(c.skeleton.names)
    return c, m, body_parts(c, m)


# --- triangle intersection ------------------------------------------------------------------------------


def test_triangles_intersect_known_cases() -> None:
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    through = np.array([[0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]])  # pierces the flat one
    above = through + np.array([0, 0, 1.0])
    beside = through + np.array([2.0, 0, 0])
    ta = np.stack([flat, flat, flat])
    tb = np.stack([through, above, beside])
    assert triangles_intersect(ta, tb).tolist() == [True, False, False]
    assert triangles_intersect(tb, ta).tolist() == [True, False, False]


def test_intersecting_pairs_match_brute_force() -> None:
    rng = np.random.default_rng(3)
    verts = np.repeat(rng.uniform(0, 1, (400, 3)), 3, axis=0) + rng.normal(0, 0.06, (1200, 3))
    fa = np.arange(600).reshape(-1, 3)
    fb = np.arange(600, 1200).reshape(-1, 3)
    got = {tuple(p) for p in intersecting_pairs(verts, fa, fb).tolist()}
    a, b = np.meshgrid(np.arange(200), np.arange(200), indexing="ij")
    hit = triangles_intersect(verts[fa[a.ravel()]], verts[fb[b.ravel()]])
    brute = set(zip(a.ravel()[hit].tolist(), b.ravel()[hit].tolist(), strict=True))
    assert got == brute and len(brute) > 5
    assert len(intersecting_pairs(verts, fa, fb, first_only=True)) >= 1


# --- hand self-contacts -----------------------------------------------------------------------------------


def _posed_clip(ch: Character, grot: torch.Tensor, gpos: torch.Tensor) -> torch.Tensor:
    return ch.pose_vertices(grot, gpos)


def test_box_hand_contacts_follow_the_papers_rules() -> None:
    ch, mapping = two_boxes()
    parts = body_parts(ch, mapping)
    frames = 8
    # Pressed 1 cm in and moving together (the whole body translates): a contact, 3 closest pairs.
    grot, gpos = box_pose(0.01, frames)
    gpos = gpos + torch.linspace(0, 0.2, frames)[:, None, None] * torch.tensor([1.0, 0.0, 0.0])
    sc = detect_self_contacts(parts, _posed_clip(ch, grot, gpos), ch.height, 30.0)
    assert sc.count == frames
    assert set(sc.part_names[h] for h in sc.hand.tolist()) == {"LeftHand"}
    assert set(sc.part_names[o] for o in sc.other.tolist()) == {"Hips"}
    assert sc.pairs.shape == (frames, 3, 2) and bool(sc.intersecting.all())
    assert float(sc.cosine.min()) > 0.9
    hand = parts.part_vertices(parts.index("LeftHand"))
    assert torch.isin(sc.pairs[..., 0], hand).all() and not torch.isin(sc.pairs[..., 1], hand).any()
    # Pressed in but only the hand moves (sliding through the other box): not a contact.
    grot, gpos = box_pose(0.01, frames)
    gpos[:, 2, 0] += torch.linspace(0, 0.1, frames)
    assert detect_self_contacts(parts, _posed_clip(ch, grot, gpos), ch.height, 30.0).count == 0
    # Not intersecting: a contact only within the distance threshold (0.2 cm at 1.38 m, scaled to the body).
    threshold = 0.002 * ch.height / 1.38
    for gap, expected in ((0.5 * threshold, frames), (3 * threshold, 0)):
        grot, gpos = box_pose(-gap, frames)
        sc = detect_self_contacts(parts, _posed_clip(ch, grot, gpos), ch.height, 30.0)
        assert sc.count == expected, gap
        if expected:
            assert not bool(sc.intersecting.any())
            assert torch.allclose(sc.distance[:, 0], torch.full((frames,), gap), atol=1e-5)


@pytest.mark.parametrize("side", ["Left", "Right"])
def test_hand_placed_on_the_hip_is_detected(average, side: str) -> None:
    ch, mapping, parts = average
    local_r, local_t, hip_vertex = hand_on_hip_pose(ch, mapping, parts, side)
    grot, gpos = kinematics.forward_kinematics(ch.skeleton.parents, local_r, local_t)
    frames = 6
    posed = ch.pose_vertices(grot, gpos)[None].repeat(frames, 1, 1)
    posed = posed + torch.linspace(0, 0.1, frames)[:, None, None] * torch.tensor([0.0, 0.0, 1.0])  # walking on
    sc = detect_self_contacts(parts, posed, ch.height, 30.0)
    hand = parts.index(f"{side}Hand")
    touched = {sc.part_names[o] for o in sc.other[sc.hand == hand].tolist()}
    assert "Hips" in touched, sc.summary()
    assert touched <= {"Hips", f"{side}UpLeg", "Spine"}, sc.summary()
    assert int(sc.frames_with_contact().sum()) == frames
    # The closest pairs lie where the hand meets the hip, within a few centimetres of the chosen point.
    on_hip = sc.pairs[(sc.hand == hand) & (sc.other == parts.index("Hips"))]
    assert float((posed[0, on_hip[..., 1].flatten()] - posed[0, hip_vertex]).norm(dim=1).min()) < 0.10
    assert float(sc.distance.max()) < 0.02


def test_rest_pose_has_no_self_contact(average) -> None:
    ch, _, parts = average
    rr, rp = ch.skeleton.rest_global()
    posed = ch.pose_vertices(rr, rp)[None].repeat(4, 1, 1)
    assert detect_self_contacts(parts, posed, ch.height, 30.0).count == 0


def test_two_hand_grip_in_swordplay_clip(shared_data: Path) -> None:
    """CMU 02_08 (swordplay): the built-in body driven by the clip holds the sword with both hands."""
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.loading import load_character, load_motion

    source = load_character("builtin:male_average")
    motion = load_motion(shared_data / "motions" / "cmu" / "002_08.bvh").motion
    mapping = load_motion(shared_data / "motions" / "cmu" / "002_08.bvh").mapping
    copied = copy_retarget(motion, mapping, source.character.skeleton, source.mapping)
    grot, gpos = copied.global_transforms()
    step = 2  # 60 -> 30 fps
    posed = source.character.pose_vertices(grot[150:450:step], gpos[150:450:step])
    sc = detect_self_contacts(body_parts(source.character, source.mapping), posed, source.character.height, copied.fps / step)
    both = [e for e in sc.summary() if {e["hand"], e["other"]} == {"LeftHand", "RightHand"}]
    assert both and max(e["frames"] for e in both) >= 20, sc.summary()


# --- foot contacts ----------------------------------------------------------------------------------------


def _foot_mapping() -> JointMapping:
    return JointMapping({"LeftFoot": 0, "LeftToeBase": 1, "RightFoot": 2, "RightToeBase": 3})


def test_foot_planted_then_lifted() -> None:
    f = 40
    rest = torch.tensor([[0.1, 0.08, 0.0], [0.1, 0.03, 0.12], [-0.1, 0.08, 0.0], [-0.1, 0.03, 0.12]])
    pos = rest.repeat(f, 1, 1)
    lift = torch.arange(20, dtype=torch.float32) * 0.015  # 1.5 cm per frame from frame 20 on
    pos[20:, 0, 1] += lift
    pos[20:, 1, 1] += lift
    fc = detect_foot_contacts(pos, rest, _foot_mapping(), height=1.8, fps=30.0)
    lt, lh, rt, rh = fc.labels.T
    assert fc.names == ("left_toe", "left_heel", "right_toe", "right_heel")
    assert lt[:20].all() and not lt[21:].any()  # 1.5 cm/frame > 1 cm: lifted from the first moving frame
    assert lh[:20].all() and not lh[21:].any()
    assert rt.all() and rh.all()  # the right foot stays planted
    # Toe height alone: a toe hovering 4 cm up without moving is not in contact; 2 cm up it is.
    for height, expected in ((0.04, False), (0.02, True)):
        p = rest.repeat(10, 1, 1)
        p[:, 1, 1] += height
        assert bool(detect_foot_contacts(p, rest, _foot_mapping(), 1.8, 30.0).labels[:, 0].all()) == expected


def test_foot_thresholds_scale_with_body_and_frame_rate() -> None:
    rest = torch.zeros(4, 3)
    pos = rest.repeat(30, 1, 1)
    pos[:, 0, 0] = torch.arange(30) * 0.007  # heel slides 7 mm per frame
    mapping = _foot_mapping()
    assert detect_foot_contacts(pos, rest, mapping, 1.8, 30.0).labels[:, 1].all()  # under 1 cm/frame at 30 fps
    assert not detect_foot_contacts(pos, rest, mapping, 1.8, 60.0).labels[:, 1].any()  # 0.5 cm at 60 fps
    assert not detect_foot_contacts(pos, rest, mapping, 0.9, 30.0).labels[:, 1].any()  # half-size body
    missing = detect_foot_contacts(pos, rest, JointMapping({"LeftFoot": 0}), 1.8, 30.0)
    assert missing.available.tolist() == [False, True, False, False] and not missing.labels[:, 0].any()


def test_window_fills_short_gaps_only() -> None:
    x = torch.tensor([1, 1, 0, 1, 1, 0, 0, 0, 1, 1], dtype=torch.bool)[:, None]
    out = fill_window(x, 5)[:, 0].tolist()
    assert out[2] is True  # one missing frame among contacts
    assert out[5:8] == [False, False, False]
    assert fill_window(torch.zeros(0, 4, dtype=torch.bool)).shape == (0, 4)
    assert FootContactParams().window == 5


# --- correspondence ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def skinny_bulky():
    a, b = load_preset("female_skinny"), load_preset("male_bulky")
    return a, mapping_by_name(a.skeleton.names), b, mapping_by_name(b.skeleton.names)


def test_correspondence_between_body_shapes(skinny_bulky) -> None:
    """The MakeHuman bodies share their topology, so vertex i of one is vertex i of the other: the truth."""
    a, ma, b, mb = skinny_bulky
    corr = build_correspondence(a, ma, b, mb)
    idx = corr.map(torch.arange(a.num_vertices))
    err = (b.vertices[idx] - b.vertices).norm(dim=1)
    assert float(err.median()) < 0.015
    parts = body_parts(b, mb)
    for hand in ("LeftHand", "RightHand"):
        assert float(err[parts.group(hand)].median()) < 0.01
    same = build_correspondence(b, mb, b, mb).map(torch.arange(b.num_vertices))
    assert torch.equal(same, torch.arange(b.num_vertices))


def test_correspondence_across_topologies(skinny_bulky) -> None:
    """Target remeshed (each triangle split in four): original vertices keep their index and place."""
    a, ma, b, mb = skinny_bulky
    verts, faces = trimesh.remesh.subdivide(b.vertices.numpy(), b.faces.numpy())
    dense = b.dense_weights().numpy()
    edges = np.sort(np.concatenate([b.faces.numpy()[:, [0, 1]], b.faces.numpy()[:, [1, 2]], b.faces.numpy()[:, [2, 0]]]), axis=1)
    edges = np.unique(edges, axis=0)
    # Each new vertex is the midpoint of an edge: it takes the mean of the edge's two skinning weights.
    from scipy.spatial import cKDTree

    dist, which = cKDTree(b.vertices.numpy()[edges].mean(1)).query(verts[len(dense) :])
    assert dist.max() < 1e-6
    w = torch.tensor(np.concatenate([dense, dense[edges[which]].mean(1)]), dtype=torch.float32)
    j = torch.arange(w.shape[1]).repeat(len(w), 1)
    fine = Character("fine", b.skeleton, torch.tensor(verts, dtype=torch.float32), torch.tensor(faces), j, w)
    idx = build_correspondence(a, ma, fine, mb).map(torch.arange(a.num_vertices))
    err = (fine.vertices[idx] - b.vertices).norm(dim=1)
    assert float(err.median()) < 0.015


def test_transfer_contacts_maps_every_pair(skinny_bulky) -> None:
    ch, mapping = two_boxes()
    parts = body_parts(ch, mapping)
    grot, gpos = box_pose(0.01, 3)
    sc = detect_self_contacts(parts, ch.pose_vertices(grot, gpos), ch.height, 30.0)
    corr = build_correspondence(ch, mapping, ch, mapping)
    cons = transfer_contacts(sc, corr)
    assert cons.count == sc.count * 3
    assert torch.equal(cons.i, sc.pairs[..., 0].reshape(-1)) and torch.equal(cons.j, sc.pairs[..., 1].reshape(-1))
    assert torch.equal(cons.frame, sc.frame.repeat_interleave(3))
    part = cons.select_frames(1, 3)
    assert part.num_frames == 2 and part.count == 6 and int(part.frame.max()) == 1
