"""Props above the floor (retarget_core/refine/props.py): a staff on a bone of its own under the right hand of a
MakeHuman body, its foot below the floor on the frames where the body bobs down, turned at its grip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from retarget_core.bodies import load_preset
from retarget_core.body_parts import mapping_by_name
from retarget_core.character import Character
from retarget_core.mesh_roles import MeshSpan, with_mesh_roles
from retarget_core.motion import Motion
from retarget_core.refine import props
from retarget_core.skeleton import Skeleton

FRAMES = 150
DIP = slice(45, 105)  # the frames the body bobs down over


def with_staff(body: Character, length: float, grip: float) -> Character:
    """``body`` holding a staff ``length`` long in its right hand, ``grip`` below its top, plumb in the rest pose,
    on a joint of its own (``Staff``, at the hand)."""
    sk = body.skeleton
    hand = sk.names.index("RightHand")
    staff = len(sk.names)
    skeleton = Skeleton([*sk.names, "Staff"], [*sk.parents, hand],
                        torch.cat([sk.rest_translations, torch.zeros(1, 3)]),
                        torch.cat([sk.rest_rotations, torch.tensor([[0.0, 0.0, 0.0, 1.0]])]))  # fmt: skip
    at = sk.rest_global()[1][hand].numpy()
    rod = trimesh.creation.cylinder(radius=0.015, height=length, sections=12)
    rod_v = np.asarray(rod.vertices)[:, [0, 2, 1]] + at + np.array([0.0, grip - length / 2, 0.0])  # along Y
    k = body.skin_joints.shape[1]
    joints = torch.zeros(len(rod_v), k, dtype=torch.long)
    joints[:, 0] = staff
    weights = torch.zeros(len(rod_v), k)
    weights[:, 0] = 1.0
    n = body.num_vertices
    ch = Character("staff bearer", skeleton, torch.cat([body.vertices, torch.as_tensor(rod_v, dtype=torch.float32)]),
                   torch.cat([body.faces, torch.as_tensor(np.asarray(rod.faces), dtype=torch.long) + n]),
                   torch.cat([body.skin_joints, joints]), torch.cat([body.skin_weights, weights]))  # fmt: skip
    spans = [MeshSpan("Body", 0, n, 0, int(body.faces.shape[0])),
             MeshSpan("Staff", n, len(rod_v), int(body.faces.shape[0]), len(rod.faces))]  # fmt: skip
    return with_mesh_roles(ch, spans)


def bobbing(character: Character, low: float, high: float) -> Motion:
    """The rest pose with the root at ``high`` above its rest height, dipping to ``low`` and back over the frames
    :data:`DIP`."""
    sk = character.skeleton
    trans = sk.rest_translations.expand(FRAMES, -1, -1).clone()
    phase = torch.linspace(0.0, 2 * math.pi, DIP.stop - DIP.start)
    trans[:, 0, 1] += high
    trans[DIP, 0, 1] += (low - high) * 0.5 * (1 - torch.cos(phase))
    return Motion(sk, 30.0, sk.rest_rotations.expand(FRAMES, -1, -1).clone(), trans, "bob")


def lowest_of(character: Character, motion: Motion, vertices: torch.Tensor) -> torch.Tensor:
    """``(F,)`` the lowest height of ``vertices``."""
    grot, gpos = motion.global_transforms()
    return character.pose_rows(vertices, grot, gpos)[..., 1].min(dim=-1).values


@pytest.fixture(scope="module")
def average() -> Character:
    return load_preset("male_average")


def test_a_staff_on_its_own_bone_is_a_prop_and_a_body_has_none(average: Character) -> None:
    ch = with_staff(average, 1.6, 0.2)
    assert [m.role for m in ch.meshes] == ["body", "accessory"]
    found = props.find_props(ch, mapping_by_name(ch.skeleton.names))
    assert [ch.skeleton.names[p.joint] for p in found] == ["Staff"]
    assert torch.equal(found[0].vertices, torch.arange(average.num_vertices, ch.num_vertices))
    assert props.find_props(average, mapping_by_name(average.skeleton.names)) == []


@pytest.mark.parametrize("grip", [0.2, 0.8], ids=["held_at_the_top", "held_at_the_middle"])
def test_a_staff_below_the_floor_is_turned_above_it_smoothly(average: Character, grip: float) -> None:
    """Every frame's staff ends at or above the floor (gripped at its middle, both ends: the turn stays within the
    band where the upper end stays up too); the body's joints keep their rotations and the root its path bit for
    bit; frames a second from any sunk one are left alone; the turn eases in and out (no step between frames larger
    than the need's own)."""
    ch = with_staff(average, 1.6, grip)
    staff = torch.arange(average.num_vertices, ch.num_vertices)
    motion = bobbing(ch, -0.5 if grip > 0.5 else -0.1, 0.45)
    before = lowest_of(ch, motion, staff)
    assert float(before.min()) < -0.2 and float(before.max()) > 0.05  # sunk on some frames, clear on others
    ctx = type("Ctx", (), {"target": ch, "target_mapping": mapping_by_name(ch.skeleton.names)})()
    out = props.run(ctx, motion)  # type: ignore[arg-type]
    after = lowest_of(ch, out.motion, staff)
    assert float(after.min()) >= -0.001
    body = [j for j in range(ch.skeleton.num_joints) if ch.skeleton.names[j] != "Staff"]
    assert torch.equal(out.motion.rotations[:, body], motion.rotations[:, body])
    assert torch.equal(out.motion.translations, motion.translations)
    far = torch.cat([torch.arange(15), torch.arange(FRAMES - 15, FRAMES)])  # a second from the dip
    assert torch.equal(out.motion.rotations[far], motion.rotations[far])
    staff_j = ch.skeleton.names.index("Staff")
    turn = torch.rad2deg(2 * torch.acos(out.motion.rotations[:, staff_j, 3].abs().clamp(max=1.0)))
    assert float(turn.max()) < 60.0 and float(turn.diff().abs().max()) < 5.0  # the least turn (about 47 degrees) needs
    assert out.report["props"] == ["Staff"] and out.report["frames_changed"] > 0
