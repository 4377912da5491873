"""The collision stage measures the judge's pairs only, prices a penetrating pair at the input's depth, and
pulls end effectors toward the source's positions relative to the hips, less so for a hand in contact (small
built cases)."""

from __future__ import annotations

import roma
import torch

from retarget_core import kinematics
from retarget_core.body_parts import CLUSTERS
from retarget_core.geometry.judged_pairs import judged_allowed, judged_cluster_table
from retarget_core.geometry.point_poser import PointPoser
from retarget_core.geometry.triples import candidate_triples, penetration_energy
from retarget_core.motion import Motion
from retarget_core.refine.collision_problem import ee_targets
from tests.core.test_collisions import _arm_boxes, _context, _pushed_in


def test_judged_table_tests_limbs_and_the_head_never_the_torso() -> None:
    t = judged_cluster_table()
    c = CLUSTERS.index
    assert not bool(t[c("torso")].any())
    assert (
        bool(t[c("left_arm"), c("torso")])
        and bool(t[c("left_arm"), c("right_arm")])
        and bool(t[c("left_arm"), c("head")])
    )
    assert bool(t[c("left_leg"), c("right_leg")]) and bool(t[c("left_leg"), c("left_arm")])
    assert not bool(t[c("left_leg"), c("torso")]) and not bool(t[c("head"), c("left_arm")])
    assert bool(t[c("head"), c("torso")])


def test_judged_allowed_keeps_the_hand_in_the_torso_and_drops_the_torso_in_the_hand() -> None:
    ch = _arm_boxes()
    ctx = _context(ch, _pushed_in(ch, 0.02, frames=2))
    parts, allowed = ctx.parts, judged_allowed(ctx.sdf)
    hand, hips = parts.find("LeftHand"), parts.find("Hips")
    assert bool(ctx.sdf.allowed[hips, hand]) and not bool(allowed[hips, hand])
    assert bool(allowed[hand, hips]) == bool(ctx.sdf.allowed[hand, hips]) is True
    assert not bool((allowed & ~ctx.sdf.allowed).any())


def _penetration_at_input() -> float:
    ch = _arm_boxes()
    before = _pushed_in(ch, 0.02, frames=3)
    ctx = _context(ch, before)
    points = torch.arange(ch.num_vertices)
    poser = PointPoser(ch, points, ctx.parts.joints)
    local = roma.unitquat_to_rotmat(before.rotations.float())
    with torch.no_grad():
        posed, seg_mats, _ = poser(local, before.translations.float())
    exempt = torch.zeros(3, ctx.parts.num_parts, len(CLUSTERS), dtype=torch.bool)
    triples = candidate_triples(ctx.sdf, points, posed, seg_mats, torch.arange(3), exempt, ctx.sdf.allowed, 0.05,
                                0.001, -0.001)  # fmt: skip
    return float(penetration_energy(ctx.sdf, triples, posed, seg_mats, 1.0))


def test_a_penetrating_pair_costs_at_the_input_depth() -> None:
    assert _penetration_at_input() > 1.0  # 2 cm deep: every pair is pushed out, the head in the torso too


def test_end_effector_targets_follow_the_source_relative_to_the_hips() -> None:
    ch = _arm_boxes()
    before = _pushed_in(ch, 0.02, frames=4)
    src_rot = before.rotations.clone()
    src_rot[:, 2] = roma.rotvec_to_unitquat(torch.tensor([0.0, 0.0, 0.3]))  # the source's arm higher
    src_tr = before.translations.clone()
    src_tr[:, 0] += torch.tensor([1.0, 0.0, 0.5])  # elsewhere in the world: only hips-relative positions count
    ctx = _context(ch, before)
    ctx.source_view = Motion(ch.skeleton, 30.0, src_rot, src_tr, "src")
    frames = torch.tensor([1, 3])
    _, g_in = kinematics.forward_kinematics(ch.skeleton.parents, before.rotations[frames], before.translations[frames])
    _, g_src = kinematics.forward_kinematics(ch.skeleton.parents, src_rot[frames], src_tr[frames])
    hand = ctx.target_mapping.joints["LeftHand"]
    assert torch.allclose(ee_targets(ctx, g_in, frames, ["LeftHand"], {"LeftHand": 0.0})[:, 0], g_in[:, hand])
    full = ee_targets(ctx, g_in, frames, ["LeftHand"], {"LeftHand": 1.0})[:, 0]
    assert torch.allclose(full - g_in[:, 0], g_src[:, hand] - g_src[:, 0], atol=1e-5)
    half = ee_targets(ctx, g_in, frames, ["LeftHand"], {"LeftHand": 0.5})[:, 0]
    assert torch.allclose(half, 0.5 * (full + g_in[:, hand]), atol=1e-5)
    # A name without a pull (the feet by default) stays at the input's position.
    assert torch.allclose(ee_targets(ctx, g_in, frames, ["LeftHand"], {})[:, 0], g_in[:, hand])


def test_a_hand_in_contact_is_placed_by_its_contact_not_its_end_effector_target() -> None:
    from retarget_core.refine.collision_check import ContactInstances
    from retarget_core.refine.collision_params import CollisionParams
    from retarget_core.refine.collision_problem import ee_weights

    ch = _arm_boxes()
    ctx = _context(ch, _pushed_in(ch, 0.02, frames=5))
    hand = ctx.parts.find("LeftHand")
    contacts = ContactInstances(torch.tensor([1, 2]), torch.tensor([hand, hand]), torch.tensor([1, 1]))
    params = CollisionParams()
    w = ee_weights(ctx, contacts, torch.tensor([0, 2, 4]), ["LeftHand", "Head"], params)
    assert w.shape == (3, 2)
    assert w[:, 1].eq(params.end_effectors["Head"]).all()
    expected = [params.end_effectors["LeftHand"], params.contact_ee_weight, params.end_effectors["LeftHand"]]
    assert torch.allclose(w[:, 0], torch.tensor(expected))


def test_candidate_triples_are_every_point_within_the_slack_of_an_allowed_segment() -> None:
    """The compiled search (:func:`retarget_core.energy.pair_samples_kernel.segment_triples`) keeps exactly the
    (segment, frame, point) triples a brute force over every one keeps: the point within the slack of the
    segment's grid box and its blended distance below the slack (``only_penetrating``: deeper than the bind
    pose), frames then points in order."""
    from retarget_core.energy.sdf import segment_distance

    ch = _arm_boxes()
    before = _pushed_in(ch, 0.02, frames=3)
    ctx = _context(ch, before)
    sdf, points = ctx.sdf, torch.arange(ch.num_vertices)
    poser = PointPoser(ch, points, ctx.parts.joints)
    with torch.no_grad():
        posed, seg_mats, _ = poser(roma.unitquat_to_rotmat(before.rotations.float()), before.translations.float())
    exempt = torch.zeros(3, ctx.parts.num_parts, len(CLUSTERS), dtype=torch.bool)
    part = ctx.parts.vertex_part
    hi_all = sdf.origin + (sdf.size - 1).to(sdf.origin.dtype) * sdf.voxel[:, None]
    for only in (False, True):
        got = candidate_triples(sdf, points, posed, seg_mats, torch.arange(3), exempt, sdf.allowed, 0.05, 0.001,
                                -0.001, only_penetrating=only)  # fmt: skip
        want = []
        for j in range(ctx.parts.num_parts):
            if sdf.grids[j] is None:
                continue
            m = seg_mats[:, j].double()
            local = torch.einsum("fji,fnj->fni", m[..., :3], posed.double() - m[:, None, :, 3])
            gap = (local - torch.maximum(torch.minimum(local, hi_all[j].double()), sdf.origin[j].double())).norm(dim=-1)
            f, p = torch.nonzero((gap <= 0.05) & sdf.allowed[part, j][None], as_tuple=True)
            d = segment_distance(sdf, j, local[f, p])
            keep = (-d - sdf.rest_depth[p, j].double() > 0) if only else d < 0.05
            want += [(j, int(a), int(b)) for a, b in zip(f[keep], p[keep], strict=True)]
        have = [(j, int(a), int(b)) for j, f, p, *_ in got.groups for a, b in zip(f, p, strict=True)]
        assert have == want and len(want) > 0
