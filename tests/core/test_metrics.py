"""Quality metrics and the metrics JSON on constructed motions with known answers, and on the shared data."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from retarget_core import kinematics
from retarget_core.bodies import load_preset
from retarget_core.body_parts import body_parts, mapping_by_name
from retarget_core.contacts.correspondence import ContactConstraints
from retarget_core.contacts.foot_contact import FootContacts
from retarget_core.energy.sdf import build_part_sdf
from retarget_core.metrics.compute import compute_metrics, measure_clip, summarize
from retarget_core.metrics.report import (
    SCHEMA_VERSION,
    MetricsReport,
    build_metrics_report,
    read_metrics_json,
    write_metrics_json,
)
from retarget_core.motion import Motion

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest_contacts import box_pose, hand_on_hip_pose, two_boxes  # noqa: E402


@pytest.fixture(scope="module")
def boxes():
    ch, mapping = two_boxes()
    parts = body_parts(ch, mapping)
    return ch, mapping, build_part_sdf(ch, parts)


def box_motion(ch, depths: list[float]) -> Motion:  # type: ignore[no-untyped-def]
    """The two-box character with the small box pushed ``depths[f]`` into the big one at frame f."""
    gpos = torch.cat([box_pose(d)[1] for d in depths])
    grot = box_pose(0.0)[0].expand(len(depths), 3, 4)
    lr, lt = kinematics.global_to_local(ch.skeleton.parents, grot, gpos)
    return Motion(ch.skeleton, 30.0, lr, lt, "boxes")


def test_penetration_and_collision_metrics_of_boxes(boxes) -> None:
    ch, mapping, sdf = boxes
    s = 1.80 / ch.height
    m = measure_clip(ch, mapping, sdf, box_motion(ch, [-0.01, 0.01, 0.02, 0.03]))
    summary = summarize(m).summary
    assert summary.penetration_max_depth.value == pytest.approx(3.0, abs=0.1)
    assert summary.penetration_max_depth.value_at_180 == pytest.approx(3.0 * s, abs=0.1 * s)
    assert summary.penetration_mean_depth.value == pytest.approx((0 + 1 + 2 + 3) / 4, abs=0.1)
    assert summary.penetrating_frames_percent == pytest.approx(75.0)
    # Paper 2: the left arm's end segment (the hand box) collides with the torso (the big box) in 3 frames.
    assert summary.m_c.value == pytest.approx((1 + 4 + 9) / 3, rel=0.02)
    assert summary.m_c.unit == "cm^2" and summary.m_c.value_at_180 == pytest.approx(summary.m_c.value * s * s, rel=1e-3)
    assert summary.m_i.value == pytest.approx(summary.m_c.value, rel=1e-6) and summary.m_o.value == 0.0
    series = summarize(m).series
    assert series["penetration_max_depth"].values == pytest.approx([0.0, 1 * s, 2 * s, 3 * s], abs=0.1)
    assert summary.foot_contact_accuracy is None and summary.foot_skate.value is None  # no feet on boxes
    assert summary.mpjpe.value is None and summary.global_position_error.value is None


def test_after_is_measured_against_the_original(boxes) -> None:
    ch, mapping, sdf = boxes
    before = measure_clip(ch, mapping, sdf, box_motion(ch, [-0.01, 0.01, 0.02, 0.03]))
    after = measure_clip(ch, mapping, sdf, box_motion(ch, [-0.01, -0.005, 0.005, 0.01]))
    summary = summarize(after, original=before, reference=before).summary
    # Frames 1-3 collided before; after, they are 0.5 cm apart, 0.5 cm and 1 cm in (paper 2's M_i / M_o).
    assert summary.m_i.value == pytest.approx((0 + 0.25 + 1) / 3, rel=0.03)
    assert summary.m_o.value == pytest.approx(0.25 / 3, rel=0.05)
    assert summary.m_c.value == pytest.approx((0.25 + 1) / 2, rel=0.03)
    # Only the hand joint moved (by 0, 1.5, 1.5, 2 cm): MPJPE averages over the 3 joints, hips-relative.
    expected = (0 + 1.5 + 1.5 + 2) / 4 / 3
    assert summary.mpjpe.value == pytest.approx(expected, rel=1e-3)
    assert summary.global_position_error.value == pytest.approx(expected, rel=1e-3)
    assert summary.global_position_mse.value == pytest.approx((0 + 2.25 + 2.25 + 4) / 4 / 3, rel=1e-3)


def test_contact_distance_metric(boxes) -> None:
    ch, mapping, sdf = boxes
    motion = box_motion(ch, [-0.01, -0.02])
    hand = torch.nonzero(ch.skin_joints[:, 0] == 2).flatten()
    bottom = hand[ch.vertices[hand, 1] < ch.vertices[hand, 1].min() + 1e-6][:1]
    top_centre = torch.nonzero((ch.vertices - torch.tensor([0.0, 0.4, 0.0])).norm(dim=1) < 1e-6).flatten()
    i, j = int(bottom[0]), int(top_centre[0])
    cons = ContactConstraints(2, torch.tensor([0, 1]), torch.tensor([i, i]), torch.tensor([j, j]), torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long), [])
    m = measure_clip(ch, mapping, sdf, motion, cons)
    grot, gpos = motion.global_transforms()
    posed = ch.pose_vertices(grot, gpos)
    expected = (posed[:, i] - posed[:, j]).norm(dim=-1) * 100
    out = summarize(m)
    assert out.summary.contact_distance_mean.value == pytest.approx(float(expected.mean()), rel=1e-4)
    assert out.summary.contact_pairs == 2 and out.summary.contact_frames == 2
    assert out.series["contact_distance"].values == pytest.approx((expected * 1.8 / ch.height).tolist(), rel=1e-3)


@pytest.fixture(scope="module")
def average_body():
    ch = load_preset("male_average")
    mapping = mapping_by_name(ch.skeleton.names)
    return ch, mapping, build_part_sdf(ch, body_parts(ch, mapping))


def _sliding(ch, step: float, drop: float, frames: int = 12, accel: float = 0.0) -> Motion:  # type: ignore[no-untyped-def]
    rot = ch.skeleton.rest_rotations.expand(frames, -1, -1).clone()
    trans = ch.skeleton.rest_translations.expand(frames, -1, -1).clone()
    t = torch.arange(frames, dtype=torch.float32)
    trans[:, 0, 2] += step * t + 0.5 * accel * t**2
    trans[:, 0, 1] -= drop
    return Motion(ch.skeleton, 30.0, rot, trans, "slide")


def test_foot_skate_ground_penetration_and_accuracy(average_body) -> None:
    ch, mapping, sdf = average_body
    s = 1.80 / ch.height
    planted = FootContacts(torch.ones(12, 4, dtype=torch.bool), [mapping.joints[n] for n in ("LeftToeBase", "LeftFoot", "RightToeBase", "RightFoot")])
    m = measure_clip(ch, mapping, sdf, _sliding(ch, 0.005, 0.02))
    out = summarize(m, source_feet=planted).summary
    assert out.foot_skate.value == pytest.approx(0.5, rel=1e-3)
    assert out.foot_skate.value_at_180 == pytest.approx(0.5 * s, rel=1e-3)
    assert out.ground_penetration_max.value == pytest.approx(2.0, abs=1e-3)
    assert out.ground_penetration_mean.value == pytest.approx(2.0, abs=1e-3)
    assert out.foot_contact_accuracy == pytest.approx(1.0)  # slow enough and low enough to be planted
    fast = summarize(measure_clip(ch, mapping, sdf, _sliding(ch, 0.03, 0.0)), source_feet=planted).summary
    assert fast.foot_contact_accuracy == pytest.approx(0.0)
    assert fast.foot_skate.value == pytest.approx(3.0, rel=1e-3)
    assert fast.ground_penetration_max.value == pytest.approx(0.0, abs=1e-4)
    assert out.penetration_max_depth.value == pytest.approx(0.0, abs=0.05)  # the rest pose has no penetration


def test_acceleration_and_jerk(average_body) -> None:
    ch, mapping, sdf = average_body
    m = measure_clip(ch, mapping, sdf, _sliding(ch, 0.0, 0.0, frames=8, accel=0.002))
    out = summarize(m).summary
    assert out.acceleration.value == pytest.approx(0.2, rel=1e-3)  # cm per frame^2
    assert out.jerk.value == pytest.approx(0.0, abs=1e-4)


def test_report_round_trip(boxes, tmp_path: Path) -> None:
    ch, mapping, sdf = boxes
    before = measure_clip(ch, mapping, sdf, box_motion(ch, [0.01, 0.02]))
    after = measure_clip(ch, mapping, sdf, box_motion(ch, [-0.01, 0.005]))
    report = build_metrics_report(
        "boxes", ch.name, ch.height, summarize(before), summarize(after, original=before), timings_s={"metrics": 0.1}
    )
    assert report.schema_version == SCHEMA_VERSION == "1.0"
    assert report.scale_to_180 == pytest.approx(1.8 / ch.height, rel=1e-5)
    assert report.improvement["penetration_max_depth"] < 0  # after is better
    path = write_metrics_json(report, tmp_path / "m" / "metrics.json")
    raw = json.loads(path.read_text())
    assert raw["before"]["summary"]["contact_distance_mean"] == {"value": None, "value_at_180": None, "unit": "cm"}
    assert raw["after"]["summary"]["mpjpe"]["value"] > 0
    assert len(raw["before"]["series"]["penetration_max_depth"]["values"]) == 2
    assert read_metrics_json(path) == report
    light = build_metrics_report("boxes", ch.name, ch.height, summarize(before), include_series=False)
    assert light.before.series == {} and light.after is None and light.improvement == {}
    with pytest.raises(ValueError):
        MetricsReport.model_validate({**raw, "schema_version": "0.9"})


def test_measure_job_carries_source_contacts_to_the_target() -> None:
    from retarget_core.evaluation import measure_job

    src = load_preset("male_average")
    src_map = mapping_by_name(src.skeleton.names)
    local_r, local_t, _ = hand_on_hip_pose(src, src_map, body_parts(src, src_map), "Left")
    frames = 5
    view = Motion(src.skeleton, 30.0, local_r.expand(frames, -1, -1).clone(), local_t.expand(frames, -1, -1).clone(), "hand_on_hip")
    tgt = load_preset("male_bulky")
    tgt_map = mapping_by_name(tgt.skeleton.names)
    before = Motion(tgt.skeleton, 30.0, view.rotations.clone(), tgt.skeleton.rest_translations.expand(frames, -1, -1).clone(), "hand_on_hip")
    job = measure_job(src, src_map, view, tgt, tgt_map, before, before)
    r = job.report
    assert r.source_contacts.self_contacts >= frames
    assert r.source_contacts.constraints == 3 * r.source_contacts.self_contacts == job.constraints.count
    assert r.source_contacts.pairs[0].hand == "LeftHand"
    assert r.before.summary.contact_pairs == job.constraints.count
    assert r.before.summary.contact_distance_mean.value is not None
    assert r.after is not None and r.after.summary.mpjpe.value == pytest.approx(0.0, abs=1e-6)
    assert set(r.timings_s) == {"contacts", "correspondence", "sdf", "metrics"}
    # Hand contacts: every source contact (frame, hand, part) is measured on the target by the hand's distance to
    # the touched part; the bulky hip is wider, so the copied hand rests on or in it: kept.
    n_contacts = len({(f, h, c) for f, h, c in zip(job.source.self_contacts.frame.tolist(),
                      job.source.self_contacts.hand.tolist(), job.source.self_contacts.part.tolist(), strict=True)})  # fmt: skip
    assert r.before.summary.hand_contacts == n_contacts
    assert r.before.summary.contact_preservation == 1.0
    assert r.before.summary.contact_hand_distance_mean.value_at_180 < 2.5
    assert len(r.before.series["contact_hand_distance"].values) == frames
    # The arm back at rest (the hand away from the hip): no contact is kept.
    from retarget_core.evaluation import part_sdf_for

    rest = tgt.skeleton.rest_rotations.expand(frames, -1, -1).clone()
    away = Motion(tgt.skeleton, 30.0, rest, before.translations.clone(), "away")
    lost, _ = compute_metrics(tgt, tgt_map, part_sdf_for(tgt, tgt_map)[1], away, contacts=job.constraints)
    assert lost.summary.hand_contacts == n_contacts and lost.summary.contact_preservation == 0.0
    assert lost.summary.contact_hand_distance_mean.value_at_180 > 3.0
    assert lost.summary.false_contacts is None  # the source's distances were not given
    # False contacts: a source standing at rest (hands far from everything) whose result has the hand on the hip.
    from retarget_core.contacts.hand_distance import hand_part_distances

    rest_r, rest_p = src.skeleton.rest_global()
    still = src.pose_vertices(rest_r, rest_p)[None].expand(frames, -1, -1)
    far = hand_part_distances(src, body_parts(src, src_map), still)
    false, _ = compute_metrics(tgt, tgt_map, part_sdf_for(tgt, tgt_map)[1], before, source_hand_distances=far)
    far_pairs = int((torch.isinf(far.distance) & far.measured[None]).sum())
    assert false.summary.false_contacts is not None and far_pairs == frames * 10  # 2 hands x 5 other parts
    assert false.summary.false_contacts >= 1 / 10  # the left hand on the hip, at least
    clean, _ = compute_metrics(tgt, tgt_map, part_sdf_for(tgt, tgt_map)[1], away, source_hand_distances=far)
    assert clean.summary.false_contacts == 0.0
    with pytest.raises(ValueError, match="same number of frames"):
        measure_job(src, src_map, view, tgt, tgt_map, before.slice(0, 3))


def test_copy_baseline_penetration_grows_with_bulk(shared_data: Path) -> None:
    """The measuring stick on real data: the same clip copied onto a skinny and a bulky body."""
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.evaluation import part_sdf_for
    from retarget_core.loading import load_character, load_motion

    src = load_motion(shared_data / "motions" / "cmu" / "002_08.bvh")
    volume = {}
    for name in ("mh_female_skinny", "mh_male_bulky"):
        tgt = load_character(shared_data / "characters" / f"{name}.glb")
        motion = copy_retarget(src.motion, src.mapping, tgt.character.skeleton, tgt.mapping).slice(0, 120)
        _, sdf = part_sdf_for(tgt.character, tgt.mapping)
        summary = summarize(measure_clip(tgt.character, tgt.mapping, sdf, motion)).summary
        volume[name] = summary.penetration_volume.value_at_180
    assert volume["mh_male_bulky"] > 5 * volume["mh_female_skinny"], volume


def test_bulk_groups_and_index() -> None:
    from retarget_core.evaluation import bulk_groups, bulk_index

    assert bulk_groups([0.3, 0.1, 0.2, 0.7, 0.5, 0.6, 0.4]) == ["medium", "skinny", "skinny", "bulky", "medium", "bulky", "medium"]
    assert bulk_groups([2.0, 1.0]) == ["bulky", "skinny"]
    ch, _ = two_boxes()
    volume = 0.4**3 + 0.1**3
    assert bulk_index(ch) == pytest.approx(volume / ch.height**3, rel=1e-4)


def test_run_evaluation_writes_the_table(shared_data: Path, tmp_path: Path) -> None:
    from retarget_core.evaluation import run_evaluation

    table = run_evaluation(
        [shared_data / "motions" / "cmu" / "002_08.bvh"],
        [shared_data / "characters" / "mh_female_skinny.glb", shared_data / "characters" / "mh_male_bulky.glb"],
        out_dir=tmp_path,
        max_frames=40,
        log=None,
    )
    assert [r.body for r in table.rows] == ["mh_female_skinny", "mh_male_bulky"]
    assert {b.group for b in table.bodies} == {"skinny", "bulky"}
    assert table.clips[0].frames == 40 and table.clips[0].fps == 30.0
    per_body = {g.bodies: g.values["penetration_volume"] for g in table.per_body}
    assert per_body["mh_male_bulky"] > per_body["mh_female_skinny"]
    assert json.loads((tmp_path / "eval.json").read_text())["methods"] == ["copy"]
    assert "| copy | skinny |" in (tmp_path / "eval.md").read_text()
    with pytest.raises(ValueError, match="unknown method"):
        run_evaluation([], [], methods=["nope"])


def test_torch_threads_is_restored() -> None:
    from retarget_core.evaluation import torch_threads

    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("boom")
    assert torch.get_num_threads() == before
