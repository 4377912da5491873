"""A hand resting palm-down on a thigh, fingers on it: through the default chain (network + ESO, collisions,
foot lock, then finger clearance) the result's fingers do not sink into the thigh, the palm keeps its contact, and
where the hand is away from the body the finger rotations are the copy's. Whether the chain before the finger
clearance sinks a finger here depends on every stage before it (since ESO's smooth change it leaves the thumb 3.7 mm
below the palm, under the 5 mm bound), so the stage is also run on a pressed input built to need it: the chain's
result with the left hand pitched down at the wrist while it rests, its fingers pressed into the thigh.

The source: a real MakeHuman body (female_skinny) on the Mixamo rig with its fingers (MPFB2, CC0) sits, its left
hand placed palm-down on its left thigh by two-bone IK, fingers slightly curled and just touching the thigh;
then the hand lifts off and the fingers curl. The right hand is held in front, away from the body throughout.
The target: a bulky MakeHuman body on the Unreal-style rig. Measured with the independent judge's geometry
(:mod:`retarget_core.metrics.acceptance`: closed parts, winding numbers, exact distances).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core import rotations as rot
from retarget_core.canonical import FINGERS, JointMapping
from retarget_core.character import Character
from retarget_core.context import StageOutcome
from retarget_core.io.gltf_write import write_glb
from retarget_core.jobs import JobInputs
from retarget_core.mapping import map_joints
from retarget_core.metrics.acceptance import measure_pose
from retarget_core.metrics.acceptance_body import acceptance_body
from retarget_core.motion import Motion
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import prepare, refine, refine_context
from retarget_core.refine import load_stage
from retarget_core.refine.fingers import buried, finger_chains
from retarget_core.refine.two_bone_ik import two_bone_ik
from retarget_core.retargeted import Prepared
from retarget_core.skeleton import Skeleton
from retarget_core.stages import REFINEMENT_STAGE_NAMES
from tests.core.extras_rigs import about, finger_axis, finger_body

REST, LIFT, AWAY = 14, 8, 8  # frames with the hand on the thigh, lifting off, away
FRAMES = REST + LIFT + AWAY
SIT_DEG = 85.0  # thighs raised forward, shins back down
FINGER_PITCH = 0.15  # fingers' direction rises this much per unit forward: they just touch the thigh
PRESS_M = 0.003  # the palm pressed this far into the thigh (a hand resting on it)
CURL_DEG = (8.0, 40.0)  # finger curl on the thigh, and at the end of the clip (away)
REFERENCE_HEIGHT_M = 1.80
PRESS_DEG = 20.0  # the pressed input: the left hand pitched this much down at the wrist while it rests


# ------------------------------------------------------------------------------------------- the source motion


def _turn(axis: tuple[float, float, float], degrees: float) -> Tensor:
    """A rotation ``(4,)`` of ``degrees`` about ``axis``."""
    return about(torch.tensor(axis), torch.tensor([math.radians(degrees)]))[0]


def sitting(sk: Skeleton, mapping: JointMapping) -> Tensor:
    """Local rotations ``(J, 4)`` of a sitting pose: thighs forward, shins and feet as at rest."""
    local = sk.rest_rotations.clone()
    for side in ("Left", "Right"):
        up, leg = mapping.joints[f"{side}UpLeg"], mapping.joints[f"{side}Leg"]
        local[up] = rot.mul(_turn((1.0, 0.0, 0.0), -SIT_DEG), local[up])
        local[leg] = rot.mul(_turn((1.0, 0.0, 0.0), SIT_DEG), local[leg])
    return local


def hand_turn(sk: Skeleton, mapping: JointMapping, side: str, fingers: Tensor, knuckles: Tensor) -> Tensor:
    """World rotation ``(4,)`` taking the rest hand's frame (wrist to middle knuckle, pinky to index knuckle)
    onto ``fingers (3,)`` and ``knuckles (3,)``."""
    _, rp = sk.rest_global()
    pick = {n: mapping.extras[f"{side}Hand{n}1"] for n in ("Middle", "Index", "Pinky")}
    rest = rot.from_frame(
        rp[pick["Middle"]] - rp[mapping.joints[f"{side}Hand"]], rp[pick["Index"]] - rp[pick["Pinky"]], 0, 1
    )
    return rot.normalize(rot.mul(rot.from_frame(fingers, knuckles, 0, 1), rot.inv(rest)))


def dominant_joint(character: Character) -> Tensor:
    """``(V,)`` the joint with each vertex's largest skin weight."""
    return character.skin_joints.gather(1, character.skin_weights.argmax(1, keepdim=True))[:, 0]


def hand_vertices(character: Character, mapping: JointMapping, side: str) -> tuple[Tensor, Tensor]:
    """``(P,)`` palm vertices (dominant joint the hand) and ``(N,)`` finger vertices (a finger joint) of a side."""
    dom = dominant_joint(character)
    fingers = torch.tensor([j for n, j in mapping.extras.items() if n.startswith(f"{side}Hand")])
    return torch.nonzero(dom == mapping.joints[f"{side}Hand"])[:, 0], torch.nonzero(torch.isin(dom, fingers))[:, 0]


def posed(character: Character, local: Tensor, trans: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Posed vertices ``(V, 3)``, world rotations ``(J, 4)`` and positions ``(J, 3)`` of one pose."""
    g, p = kinematics.forward_kinematics(character.skeleton.parents, local, trans)
    return character.pose_vertices(g[None], p[None])[0], g, p


def palm_on_thigh(character: Character, mapping: JointMapping, local: Tensor, turn: Tensor) -> Tensor:
    """The wrist position ``(3,)`` that puts the left palm, turned by ``turn``, on the top of the left thigh of
    the pose ``local``, halfway along it, pressed ``PRESS_M`` in."""
    sk = character.skeleton
    verts, _, p = posed(character, local, sk.rest_translations)
    _, rp = sk.rest_global()
    hand = mapping.joints["LeftHand"]
    palm, _ = hand_vertices(character, mapping, "Left")
    offsets = rot.apply(turn, character.vertices[palm] - rp[hand])
    wrist = 0.5 * (p[mapping.joints["LeftUpLeg"]] + p[mapping.joints["LeftLeg"]]) - offsets.mean(0)
    thigh = verts[torch.nonzero(dominant_joint(character) == mapping.joints["LeftUpLeg"])[:, 0]]
    near = (thigh[None, :, [0, 2]] - (wrist + offsets)[:, None, [0, 2]]).norm(dim=-1) < 0.012
    top = torch.where(near, thigh[None, :, 1], torch.tensor(-math.inf)).max(1).values  # thigh top under each
    over = torch.isfinite(top)
    wrist[1] -= float((wrist[1] + offsets[over, 1] - top[over]).min()) + PRESS_M
    return wrist


def arm_to(
    character: Character, mapping: JointMapping, local: Tensor, side: str, wrist: Tensor, turn: Tensor
) -> Tensor:
    """``local (J, 4)`` with the ``side`` arm bent by two-bone IK so the wrist is at ``wrist (3,)`` and the hand
    turned by ``turn`` from its rest orientation in the world."""
    sk = character.skeleton
    _, g, p = posed(character, local, sk.rest_translations)
    rg, _ = sk.rest_global()
    arm, fore, hand = (mapping.joints[f"{side}{n}"] for n in ("Arm", "ForeArm", "Hand"))
    elbow_back = torch.tensor([0.3 if side == "Left" else -0.3, 0.0, -1.0])
    ga, gf = two_bone_ik(p[arm], p[fore], p[hand], wrist, elbow_back, g[arm], g[fore], max_reach=0.999)
    out = local.clone()
    out[arm] = rot.mul(rot.inv(g[sk.parents[arm]]), ga)
    out[fore] = rot.mul(rot.inv(ga), gf)
    out[hand] = rot.mul(rot.inv(gf), rot.mul(turn, rg[hand]))
    return rot.normalize(out)


def curled(sk: Skeleton, mapping: JointMapping, local: Tensor, degrees: Tensor) -> Tensor:
    """``local (F, J, 4)`` with every finger joint (thumbs aside) curled by ``degrees (F,)`` about its hand's
    knuckle line."""
    grot, _ = sk.rest_global()
    out = local.clone()
    for side in ("Left", "Right"):
        axis = finger_axis(sk, mapping, side)
        for name, j in mapping.extras.items():
            if name.startswith(f"{side}Hand") and "Thumb" not in name:
                turn = about(rot.apply(rot.inv(grot[j]), axis), torch.deg2rad(degrees))
                out[:, j] = rot.normalize(rot.mul(out[:, j], turn))
    return out


def pitched(sk: Skeleton, mapping: JointMapping, local: Tensor, degrees: Tensor) -> Tensor:
    """``local (F, J, 4)`` with the left hand turned down by ``degrees (F,)`` about its knuckle line (fingers
    lower, the wrist where it was)."""
    grot, _ = sk.rest_global()
    hand = mapping.joints["LeftHand"]
    turn = about(rot.apply(rot.inv(grot[hand]), finger_axis(sk, mapping, "Left")), torch.deg2rad(degrees))
    out = local.clone()
    out[:, hand] = rot.normalize(rot.mul(out[:, hand], turn))
    return out


def lift_weight() -> Tensor:
    """``(FRAMES,)`` 0 while the hand rests, rising smoothly to 1 as it lifts off, 1 away."""
    w = torch.clamp((torch.arange(FRAMES) - REST + 1) / (LIFT + 1), 0.0, 1.0)
    return w * w * (3 - 2 * w)  # smoothstep


def hand_on_thigh_motion(character: Character, mapping: JointMapping) -> Motion:
    """The source clip (see the module doc): ``FRAMES`` frames at 30 fps on ``character``'s skeleton."""
    sk = character.skeleton
    seat = sitting(sk, mapping)
    left = hand_turn(sk, mapping, "Left", torch.tensor([0.0, FINGER_PITCH, 1.0]), torch.tensor([-1.0, 0.0, 0.0]))
    right = hand_turn(sk, mapping, "Right", torch.tensor([0.0, 0.0, 1.0]), torch.tensor([-1.0, 0.0, 0.0]))
    wrist = palm_on_thigh(character, mapping, seat, left)
    _, _, p = posed(character, seat, sk.rest_translations)
    reach = p[mapping.joints["RightLeg"]] + torch.tensor([0.0, 0.35, 0.05])
    seat = arm_to(character, mapping, seat, "Right", reach, right)
    on = arm_to(character, mapping, seat, "Left", wrist, left)
    off = arm_to(character, mapping, seat, "Left", wrist + torch.tensor([0.0, 0.25, 0.05]), left)
    w = lift_weight()
    local = rot.slerp(on.expand(FRAMES, -1, -1), off.expand(FRAMES, -1, -1), w[:, None].expand(-1, sk.num_joints))
    local = curled(sk, mapping, local, CURL_DEG[0] + (CURL_DEG[1] - CURL_DEG[0]) * w)
    trans = sk.rest_translations.expand(FRAMES, -1, -1).clone()
    return Motion(sk, 30.0, local, trans, "hand_on_thigh")


# ------------------------------------------------------------------------------------------- measuring


@dataclass
class HandMeasures:
    """Per frame ``(F,)``, m at a 1.80 m character, the judge's geometry: the deepest left-finger vertex and the
    deepest left-palm vertex inside another part of the body, and the palm's distance to the left leg."""

    finger_depth: np.ndarray
    palm_depth: np.ndarray
    palm_gap: np.ndarray


def palm_gap(character: Character, mapping: JointMapping, palm: Tensor, verts: np.ndarray) -> float:
    """Distance (m, the body's scale) from the palm vertices ``palm (P,)`` of posed ``verts (V, 3)`` to the judge's
    closed left leg (0 when one is inside it)."""
    import igl

    part = acceptance_body(character, mapping).part("left_leg")
    assert part is not None
    local = np.ascontiguousarray(part.posed(verts))
    q = np.ascontiguousarray(verts[palm.numpy()])
    if (np.abs(igl.fast_winding_number(local, part.faces, q)) > 0.5).any():
        return 0.0
    tree = igl.AABB()
    tree.init(local, part.faces)
    d2, _, _ = tree.squared_distance(local, part.faces, q)
    return float(np.sqrt(d2.min()))


def hand_measures(character: Character, mapping: JointMapping, motion: Motion) -> HandMeasures:
    """:class:`HandMeasures` of ``motion`` on ``character``."""
    palm, fingers = hand_vertices(character, mapping, "Left")
    g, p = motion.global_transforms()
    scale = REFERENCE_HEIGHT_M / character.height
    out = HandMeasures(*(np.zeros(motion.num_frames) for _ in range(3)))
    with torch.no_grad():
        verts = character.pose_vertices(g, p).double().numpy()
    for f, v in enumerate(verts):
        depth = measure_pose(character, mapping, v).depth
        out.finger_depth[f] = depth[fingers.numpy()].max() * scale
        out.palm_depth[f] = depth[palm.numpy()].max() * scale
        out.palm_gap[f] = palm_gap(character, mapping, palm, v) * scale
    return out


# ------------------------------------------------------------------------------------------- the job

BOUND_M = 0.005  # fingers no deeper than the palm they hang from by more than 5 mm at 1.80 m
KEPT_M = 0.01  # the palm within 1 cm of the thigh where the source's rests on it
PALM_M = 0.001  # the stage's tolerance: it moves the palm's depth and contact at most this much
STEP_DEG = 8.0  # most a finger joint turns from one frame to the next at 30 fps on the resting frames
ON, AWAY_FRAMES = slice(0, REST), slice(REST + LIFT, FRAMES)


@dataclass
class Job:
    """The job: its prepared inputs, the default chain without the finger stage and with it (the stage runs last:
    :func:`test_the_stage_runs_last_in_the_default_chain`), the stage's outcome and the measures of each."""

    prepared: Prepared
    without: Motion
    outcome: StageOutcome
    source: HandMeasures
    before: HandMeasures
    after: HandMeasures

    @property
    def result(self) -> Motion:
        return self.outcome.motion


@pytest.fixture(scope="module")
def job(tmp_path_factory: pytest.TempPathFactory) -> Job:
    tmp = tmp_path_factory.mktemp("fingers_on_thigh")
    source = finger_body("female_skinny", "mixamo")
    smap = map_joints(source.skeleton)
    clip = hand_on_thigh_motion(source, smap)
    write_glb(source, clip, tmp / "source.glb", clip_name="sit")
    write_glb(finger_body("male_bulky", "game_engine"), None, tmp / "target.glb")
    prepared = prepare(
        JobInputs(tmp / "source.glb", tmp / "target.glb", options=RetargetOptions(stages={"fingers": False}))
    )
    without = refine(prepared).after
    outcome = load_stage("fingers")(refine_context(prepared, RetargetOptions()), without)
    target, tmap = prepared.target.character, prepared.target.mapping
    return Job(prepared, without, outcome, hand_measures(source, smap, clip), hand_measures(target, tmap, without),
               hand_measures(target, tmap, outcome.motion))  # fmt: skip


@pytest.fixture(scope="module")
def pressed(job: Job) -> Job:
    """The stage on an input built to need it, whatever the chain before it does: the chain's result with the left
    hand pitched ``PRESS_DEG`` down at the wrist while it rests (its fingers pressed into the thigh), the press
    fading out as it lifts."""
    prepared = job.prepared
    target, tmap = prepared.target.character, prepared.target.mapping
    rotations = pitched(target.skeleton, tmap, job.without.rotations, PRESS_DEG * (1.0 - lift_weight()))
    without = replace(job.without, rotations=rotations)
    outcome = load_stage("fingers")(refine_context(prepared, RetargetOptions()), without)
    return Job(prepared, without, outcome, job.source, hand_measures(target, tmap, without),
               hand_measures(target, tmap, outcome.motion))  # fmt: skip


def finger_joints(mapping: JointMapping, side: str = "") -> list[int]:
    return [j for n, j in mapping.extras.items() if n.startswith(f"{side}") and "Hand" in n]


def test_the_stage_runs_after_every_stage_that_turns_a_body_joint() -> None:
    """Only the props stage follows it: it turns a prop's own joint (a staff hung from a finger), no body joint."""
    assert REFINEMENT_STAGE_NAMES[-2:] == ("fingers", "props") and RetargetOptions().stages.enabled("fingers")


def test_the_stage_finds_every_finger_and_no_fingers_where_a_rig_has_none() -> None:
    sk = finger_body("male_bulky", "game_engine").skeleton
    chains = finger_chains(sk, map_joints(sk))
    assert [(c.side, c.finger, len(c.joints)) for c in chains] == [
        (s, f, 3) for s in ("Left", "Right") for f in FINGERS
    ]
    assert [float(c.spread.max()) > 0 for c in chains] == [c.finger == "Thumb" for c in chains]  # the CMC alone
    assert finger_chains(sk, replace(map_joints(sk), extras={})) == []  # a rig mapped without fingers


def test_only_contacts_that_bury_a_finger_beyond_its_palm_are_turned() -> None:
    """A contact (a run of frames with the finger in the body) is turned on its frames deeper than the palm by more
    than the tolerance where it goes beyond the allowance somewhere, also after the finger came near its palm's
    depth for a while; a brush that never does (a walk's fingers by the hip) is left alone."""
    mm = 0.001
    excess = torch.tensor([[0.0, 2, 6, 3, 0.5, 2, 4, 2, 0], [3.0, 3, 3, 3, 0, 0, 0, 0, 0]]).T * mm  # (F, C)
    chosen = buried(excess, torch.zeros_like(excess), 1 * mm, 5 * mm)
    assert chosen[:, 0].tolist() == [False, True, True, True, False, False, False, False, False]
    assert not chosen[:, 1].any()
    palm = torch.tensor([0.0, 0, 0, 0, 2, 2, 2, 0, 0])[:, None] * mm  # frames 3-6: the palm in the body too
    depth = torch.tensor([0.0, 2, 6, 3, 2.5, 4, 6, 2, 0])[:, None] * mm  # still in the body, near its palm at 4
    chosen = buried(depth, palm, 1 * mm, 5 * mm)[:, 0]
    assert chosen.tolist() == [False, True, True, True, False, True, True, True, False]


def test_the_source_rests_its_palm_on_the_thigh_fingers_on_it(job: Job) -> None:
    assert job.source.palm_gap[ON].max() <= 0.001 and job.source.finger_depth[ON].max() <= 0.001
    assert job.source.palm_gap[AWAY_FRAMES].min() > 0.1


def test_without_the_stage_the_pressed_fingers_sink(pressed: Job) -> None:
    """The pressed input needs the stage: fingers deeper than the bound below the palm while the hand rests."""
    assert (pressed.before.finger_depth - pressed.before.palm_depth)[ON].max() > BOUND_M


@pytest.mark.parametrize("case", ["job", "pressed"])
def test_fingers_do_not_sink_into_the_thigh(case: str, request: pytest.FixtureRequest) -> None:
    """Fingers no deeper than their palm by more than the bound; the palm's own depth is the stages' before (the
    stage drags palm vertices that fingers also skin at most its 1 mm tolerance deeper)."""
    job: Job = request.getfixturevalue(case)
    excess = job.after.finger_depth - job.after.palm_depth
    assert excess.max() <= BOUND_M, excess
    assert (job.after.palm_depth - job.before.palm_depth).max() <= PALM_M, job.after.palm_depth


@pytest.mark.parametrize("case", ["job", "pressed"])
def test_the_palm_keeps_its_contact(case: str, request: pytest.FixtureRequest) -> None:
    job: Job = request.getfixturevalue(case)
    assert job.after.palm_gap[ON].max() <= KEPT_M, job.after.palm_gap
    assert (job.after.palm_gap - job.before.palm_gap)[ON].max() <= PALM_M  # the stage lifts no palm off


def test_only_sinking_fingers_turn_and_smoothly(pressed: Job) -> None:
    job = pressed
    tmap = job.prepared.target.mapping
    fingers, left = finger_joints(tmap), finger_joints(tmap, "Left")
    others = [j for j in range(job.result.skeleton.num_joints) if j not in left]
    assert job.outcome.report["frames_changed"] > 0
    assert torch.equal(job.result.rotations[:, others], job.without.rotations[:, others])  # right hand included
    assert torch.equal(job.result.translations, job.without.translations)
    away = job.result.rotations[AWAY_FRAMES][:, fingers]
    assert torch.equal(away, job.without.rotations[AWAY_FRAMES][:, fingers])
    assert torch.allclose(away, job.prepared.before.rotations[AWAY_FRAMES][:, fingers], atol=1e-6)  # the copy's
    turn = _angle(job.result.rotations[1:, left], job.result.rotations[:-1, left])
    assert float(turn[: REST - 1].max()) <= STEP_DEG


def _angle(a: Tensor, b: Tensor) -> Tensor:
    """Angles (degrees) between rotations ``a``, ``b`` ``(..., 4)``."""
    d = rot.mul(rot.inv(a), b)
    return torch.rad2deg(2 * torch.atan2(d[..., :3].norm(dim=-1), d[..., 3].abs()))
