"""Quality metrics and the metrics JSON on constructed motions with known answers, and on the shared data."""

from __future__ import annotations

import json
import math
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
    from retarget_core.measure import measure_job

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
    assert set(r.timings_s) == {"contacts", "correspondence", "sdf", "metrics", "source"}
    assert r.source is not None and r.source.body == src.name and r.source.frames == frames
    # Hand contacts: every source contact (frame, hand, part) is measured on the target by the hand's distance to
    # the touched part; the bulky hip is wider, so the copied hand rests on or in it: kept.
    n_contacts = len({(f, h, c) for f, h, c in zip(job.source.self_contacts.frame.tolist(),
                      job.source.self_contacts.hand.tolist(), job.source.self_contacts.part.tolist(), strict=True)})  # fmt: skip
    assert r.before.summary.hand_contacts == n_contacts
    assert r.before.summary.contact_preservation == 1.0
    assert r.before.summary.contact_hand_distance_mean.value_at_180 < 2.5
    assert len(r.before.series["contact_hand_distance"].values) == frames
    # The arm back at rest (the hand away from the hip): no contact is kept.
    from retarget_core.body_cache import part_sdf_for

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
    from retarget_core.body_cache import body_assets
    from retarget_core.copy_retarget import copy_retarget
    from retarget_core.loading import load_character, load_motion

    src = load_motion(shared_data / "motions" / "cmu" / "002_08.bvh")
    volume = {}
    for name in ("mh_female_skinny", "mh_male_bulky"):
        tgt = load_character(shared_data / "characters" / f"{name}.glb")
        motion = copy_retarget(src.motion, src.mapping, tgt.character.skeleton, tgt.mapping).slice(0, 120)
        sdf = body_assets(tgt.character, tgt.mapping)[0].sdf
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
        methods=["collisions"],
        out_dir=tmp_path,
        max_frames=40,
        log=None,
    )
    assert [(r.method, r.body) for r in table.rows] == [
        ("copy", "mh_female_skinny"), ("collisions", "mh_female_skinny"),
        ("copy", "mh_male_bulky"), ("collisions", "mh_male_bulky"),
    ]  # fmt: skip
    assert {b.group for b in table.bodies} == {"skinny", "bulky"}
    assert table.clips[0].frames == 40 and table.clips[0].fps == 30.0
    copy = {g.bodies: g.values for g in table.per_body if g.method == "copy"}
    assert copy["mh_male_bulky"]["penetrating_vertices_percent"] > copy["mh_female_skinny"]["penetrating_vertices_percent"]
    assert all(r.values["pen_percent"] is not None and r.values["foot_accuracy"] is not None for r in table.rows)
    bulky = next(g for g in table.per_body if g.method == "collisions" and g.bodies == "mh_male_bulky")
    # The deep penetrations go (frames > 1 cm); the share of penetrating vertices on this two-hand grip does not:
    # see test_collisions_lower_the_judged_penetration_of_a_grip.
    assert bulky.ratios["frames_over_1cm_percent"] is not None and bulky.ratios["frames_over_1cm_percent"] < 0.5
    assert bulky.ms_per_frame and bulky.ms_per_frame > 0
    assert json.loads((tmp_path / "eval.json").read_text())["methods"] == ["copy", "collisions"]
    md = (tmp_path / "eval.md").read_text()
    assert "| copy | skinny |" in md and "## Ratios to the copy" in md
    with pytest.raises(ValueError, match="unknown method"):
        run_evaluation([], [], methods=["nope"])


@pytest.mark.xfail(strict=True, reason="known gap: on a two-hand grip (002_08) the collision stage presses the hands "
                   "into each other, and the judge counts a hand inside the other arm as penetration (pen %v about 2x "
                   "the copy's on mh_male_bulky); deep penetrations are resolved (frames > 1 cm 0.3x)")
def test_collisions_lower_the_judged_penetration_of_a_grip(shared_data: Path) -> None:
    from retarget_core.evaluation import run_evaluation

    table = run_evaluation([shared_data / "motions" / "cmu" / "002_08.bvh"],
                           [shared_data / "characters" / "mh_male_bulky.glb"], methods=["collisions"], max_frames=40,
                           log=None)  # fmt: skip
    ratio = next(g for g in table.per_body if g.method == "collisions").ratios["pen_percent"]
    assert ratio is not None and ratio < 1.0, ratio


def test_torch_threads_is_restored() -> None:
    from retarget_core.measure import torch_threads

    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("boom")
    assert torch.get_num_threads() == before


# --- penetration per body part (issue 8, part 2) -------------------------------------------------------------


def _subtree(parents: list[int], root: int) -> list[int]:
    out = []
    for j in range(len(parents)):
        k = j
        while k >= 0 and k != root:
            k = parents[k]
        if k == root:
            out.append(j)
    return out


def arm_swung(ch, mapping, side: str, degrees: float) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[no-untyped-def]
    """World rotations ``(J, 4)`` and positions ``(J, 3)`` of the rest pose with the ``side`` arm turned by
    ``degrees`` about the forward (z) axis at the shoulder (negative: the left arm swings in, through the torso)."""
    from retarget_core import rotations as rot

    grot, gpos = ch.skeleton.rest_global()
    grot, gpos = grot.clone(), gpos.clone()
    root = mapping.joints[f"{side}Arm"]
    q = rot.from_euler("xyz", torch.tensor([0.0, 0.0, degrees]))
    p0 = gpos[root].clone()
    for j in _subtree(ch.skeleton.parents, root):
        grot[j] = rot.mul(q, grot[j])
        gpos[j] = p0 + rot.apply(q, gpos[j] - p0)
    return grot, gpos


def test_penetration_is_split_by_the_part_of_each_vertex(average_body) -> None:
    """The rest pose counts nothing; the left arm swung into the torso counts (mostly) left-arm vertices, the
    right arm swung in right-arm ones; the six parts add up to the total, in the summary and per frame."""
    from retarget_core.body_parts import CLUSTERS

    ch, mapping, sdf = average_body
    rest = ch.skeleton.rest_global()
    poses = [rest, arm_swung(ch, mapping, "Left", -60.0), arm_swung(ch, mapping, "Right", 60.0)]
    grot = torch.stack([g for g, _ in poses])
    gpos = torch.stack([p for _, p in poses])
    lr, lt = kinematics.global_to_local(ch.skeleton.parents, grot, gpos)
    out = summarize(measure_clip(ch, mapping, sdf, Motion(ch.skeleton, 30.0, lr, lt, "arms_in")))
    series = {c: out.series[f"penetrating_vertices_percent_{c}"].values for c in CLUSTERS}
    assert all(series[c][0] == 0.0 for c in CLUSTERS), series  # the rest pose
    assert series["left_arm"][1] > 0.5 and series["right_arm"][1] == 0.0
    assert series["right_arm"][2] > 0.5 and series["left_arm"][2] == 0.0
    assert series["left_arm"][1] > series["torso"][1] and series["right_arm"][2] > series["torso"][2]
    for c in ("head", "left_leg", "right_leg"):
        assert series[c][1] == 0.0 and series[c][2] == 0.0
    total = out.series["penetrating_vertices_percent"].values
    for f in range(3):
        assert sum(series[c][f] for c in CLUSTERS) == pytest.approx(total[f], abs=1e-3)
    by_part = out.summary.penetrating_vertices_percent_by_part
    assert by_part is not None and list(by_part) == list(CLUSTERS)
    assert sum(by_part.values()) == pytest.approx(out.summary.penetrating_vertices_percent, abs=1e-3)
    assert by_part["left_arm"] == pytest.approx(sum(series["left_arm"]) / 3, abs=1e-3)


@pytest.mark.parametrize("body", ["mh_male_bulky", "mh_female_average", "mh_male_muscular"])
def test_a_body_standing_in_its_rest_pose_reports_no_penetration(shared_data: Path, body: str) -> None:
    from retarget_core.body_cache import part_sdf_for
    from retarget_core.loading import load_character
    from retarget_core.metrics.compute import compute_metrics

    loaded = load_character(shared_data / "characters" / f"{body}.glb")
    ch = loaded.character
    frames = 3
    rest = Motion(ch.skeleton, 30.0, ch.skeleton.rest_rotations.expand(frames, -1, -1).clone(),
                  ch.skeleton.rest_translations.expand(frames, -1, -1).clone(), "rest")  # fmt: skip
    _, sdf = part_sdf_for(ch, loaded.mapping)
    metrics, _ = compute_metrics(ch, loaded.mapping, sdf, rest)
    s = metrics.summary
    assert s.penetrating_vertices_percent == 0.0 and s.penetrating_frames_percent == 0.0
    assert s.penetration_max_depth.value == 0.0 and s.penetration_volume.value == 0.0
    assert s.penetrating_vertices_percent_by_part is not None
    assert set(s.penetrating_vertices_percent_by_part.values()) == {0.0}
    assert metrics.penetration_vertices is not None and metrics.penetration_vertices.vertex == []


# --- the source measured on its own body (issue 8, part 6) ---------------------------------------------------


def _hand_into_belly(ch, mapping, depth: float, steps: int = 150) -> torch.Tensor:  # type: ignore[no-untyped-def]
    """Local rotations ``(J, 4)``: the rest pose with the left arm bent so the hand's nearest vertex is ``depth``
    inside the front of the belly (a Spine vertex on the body's front, along its inward normal)."""
    import roma

    from retarget_core import rotations as rot

    parts = body_parts(ch, mapping)
    sk = ch.skeleton
    verts = ch.vertices
    belly = parts.part_vertices(parts.index("Spine"))
    bv = verts[belly]
    score = bv[:, 2] - 2.0 * bv[:, 0].abs()  # front (+z) and near the middle
    vertex = int(belly[int(score.argmax())])
    target = verts[vertex] - depth * ch.vertex_normals()[vertex]
    chain = [mapping.joints[f"Left{n}"] for n in ("Arm", "ForeArm", "Hand")]
    hand = parts.group("LeftHand")[::3]
    rest_rot, rest_pos = sk.rest_global()
    dense = ch.dense_weights()[hand]
    params = torch.zeros(len(chain), 3, requires_grad=True)
    opt = torch.optim.Adam([params], lr=0.05)

    def local() -> torch.Tensor:
        r = sk.rest_rotations.clone()
        for k, j in enumerate(chain):
            r[j] = rot.mul(sk.rest_rotations[j], roma.rotvec_to_unitquat(params[k]))
        return r

    for _ in range(steps):
        grot, gpos = kinematics.forward_kinematics(sk.parents, local(), sk.rest_translations)
        x = kinematics.linear_blend_skinning(verts[hand], dense, kinematics.skinning_matrices(rest_rot, rest_pos, grot, gpos))
        loss = (x - target).norm(dim=-1).min() ** 2 + 1e-3 * (x.mean(0) - target).norm() ** 2
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return local()


def _source_clip(ch, local_rot: torch.Tensor, frames: int, step: float) -> Motion:  # type: ignore[no-untyped-def]
    """``local_rot`` held for ``frames`` frames, the whole body sliding forward ``step`` per frame on the floor."""
    trans = ch.skeleton.rest_translations.expand(frames, -1, -1).clone()
    trans[:, 0, 2] += step * torch.arange(frames, dtype=torch.float32)
    return Motion(ch.skeleton, 30.0, local_rot.expand(frames, -1, -1).clone(), trans, "broken_source")


def _feet(ch, mapping, motion: Motion):  # type: ignore[no-untyped-def]
    from retarget_core.contacts.foot_contact import detect_foot_contacts

    _, gpos = motion.global_transforms()
    return detect_foot_contacts(gpos, ch.skeleton.rest_global()[1], mapping, ch.height, motion.fps)


def test_source_with_a_sunk_hand_and_skating_feet_gets_warnings(average_body) -> None:
    from retarget_core.metrics.source import SourceThresholds, measure_source

    ch, mapping, sdf = average_body
    s = 1.80 / ch.height
    frames = 12
    sunk = _source_clip(ch, _hand_into_belly(ch, mapping, 0.03), frames, 0.025)
    metrics, warnings = measure_source(ch, mapping, sunk, sdf, _feet(ch, mapping, sunk))
    assert metrics.hand_inside_frames_percent == 100.0
    assert metrics.hand_inside_frames_percent_by_hand["LeftHand"] == 100.0
    assert metrics.hand_inside_frames_percent_by_hand["RightHand"] == 0.0
    assert metrics.hand_depth_max.value > 1.0 / s  # cm on the body: more than 1 cm at 1.80 m
    assert metrics.penetrating_vertices_percent_by_part["left_arm"] > 0.0
    assert metrics.foot_slide.value == pytest.approx(2.5, rel=1e-3)  # both feet flat on the floor, sliding
    assert metrics.foot_slide_frames_percent == 100.0
    assert metrics.foot_skate.value is None  # too fast to count as planted
    names = {f.name for f in metrics.flags}
    assert names == {"hand_inside_body", "foot_slide"}, metrics.flags
    assert warnings == metrics.warnings and len(warnings) == 2
    assert any("hand is more than 1 cm inside the body" in w and "LeftHand 100 %" in w for w in warnings)
    assert any("skates" in w for w in warnings)
    # Stricter or looser thresholds move the verdict: they are the named fields.
    loose = SourceThresholds(hand_frames_percent=100.0, slide_frames_percent=100.0)
    assert measure_source(ch, mapping, sunk, sdf, _feet(ch, mapping, sunk), loose)[1] == []


def test_a_clean_source_gets_no_warnings(average_body) -> None:
    from retarget_core.metrics.source import measure_source

    ch, mapping, sdf = average_body
    still = _source_clip(ch, ch.skeleton.rest_rotations, 8, 0.0)
    metrics, warnings = measure_source(ch, mapping, still, sdf, _feet(ch, mapping, still))
    assert warnings == [] and metrics.flags == []
    assert metrics.hand_inside_frames_percent == 0.0 and metrics.penetrating_vertices_percent == 0.0
    assert metrics.foot_skate.value == pytest.approx(0.0, abs=1e-6) and metrics.jerk.value == pytest.approx(0.0, abs=1e-6)
    assert abs(metrics.foot_float_mean.value) < 0.5  # the rest pose stands on the floor


def test_source_warnings_reach_the_report_and_its_notes(average_body) -> None:
    from retarget_core.metrics.source import measure_source

    ch, mapping, sdf = average_body
    sunk = _source_clip(ch, _hand_into_belly(ch, mapping, 0.03, steps=100), 6, 0.0)
    source, warnings = measure_source(ch, mapping, sunk, sdf, _feet(ch, mapping, sunk))
    m = summarize(measure_clip(ch, mapping, sdf, sunk))
    report = build_metrics_report("broken", ch.name, ch.height, m, notes=["a pipeline note"], source=source)
    assert report.notes == ["a pipeline note", *warnings] and warnings
    again = MetricsReport.model_validate_json(report.model_dump_json())
    assert again.source is not None and again.source.flags[0].name == "hand_inside_body"


def test_a_jittering_source_is_flagged_as_jitter(average_body) -> None:
    """3 mm of noise on the root (every joint shakes with it): jerk far above the threshold and 1.8 times the
    acceleration, the signature of noise; nothing else is flagged."""
    from retarget_core.metrics.source import measure_source

    ch, mapping, sdf = average_body
    still = _source_clip(ch, ch.skeleton.rest_rotations, 30, 0.0)
    trans = still.translations.clone()
    trans[:, 0] += 0.003 * torch.randn(trans[:, 0].shape, generator=torch.Generator().manual_seed(0))
    shaky = Motion(ch.skeleton, 30.0, still.rotations, trans, "shaky")
    metrics, warnings = measure_source(ch, mapping, shaky, sdf, _feet(ch, mapping, shaky))
    assert metrics.jerk_to_acceleration == pytest.approx(1.83, abs=0.2)
    assert [f.name for f in metrics.flags] == ["jitter"], metrics.flags
    assert "jitters" in warnings[0]


def test_eval_methods_set_their_stages_and_options() -> None:
    """A method turns on exactly its stages (contacts always), and a method with settings passes them on."""
    from retarget_core.evaluation import METHODS, method_options
    from retarget_core.stages import REFINEMENT_STAGE_NAMES

    plain = method_options("collisions+foot_lock", 30.0)
    assert {n for n in REFINEMENT_STAGE_NAMES if plain.stages.enabled(n)} == {"collisions", "foot_lock"}
    assert plain.stages.enabled("contacts") and plain.eso_iterations == 30
    fewer = method_options("full[eso12]", 30.0)
    assert fewer.eso_iterations == 12
    assert {n for n in REFINEMENT_STAGE_NAMES if fewer.stages.enabled(n)} == set(METHODS["full"])


def test_unchanged_after_reuses_the_before_measures() -> None:
    """A job whose stages left the copy as it was is measured once: its "after" reads exactly as an equal
    motion measured again would (timings apart)."""
    from dataclasses import replace

    from retarget_core.jobs import JobInputs
    from retarget_core.metrics_summary import build_metrics
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import prepare, refine
    from retarget_core.stages import REFINEMENT_STAGE_NAMES

    samples = Path(__file__).resolve().parents[2] / "retarget_core" / "data" / "samples"
    off = {n: False for n in REFINEMENT_STAGE_NAMES}
    inputs = JobInputs(samples / "motions" / "007_03.bvh", samples / "characters" / "mh_male_bulky.glb",
                       options=RetargetOptions(frame_end=40, stages=off))  # fmt: skip
    result = refine(prepare(inputs))
    assert result.after is result.prepared.before
    once = build_metrics(result)
    again = build_metrics(replace(result, after=replace(result.after)))
    assert once["after"] == again["after"] and once["improvement"] == again["improvement"]


def _perturbed(motion: Motion, frames: slice, joint: int, angle: float) -> Motion:
    """``motion`` with joint ``joint`` turned by ``angle`` (radians, about x) on ``frames`` only."""
    from retarget_core import rotations as rot

    q = torch.tensor([math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0])
    r = motion.rotations.clone()
    r[frames, joint] = rot.mul(r[frames, joint], q.expand_as(r[frames, joint]))
    return Motion(motion.skeleton, motion.fps, r, motion.translations.clone(), motion.name)


def test_fast_metrics_equal_the_full_measurement(shared_data: Path) -> None:
    """The metrics path (hand distances only where the penetration queries found a hand near a part, "after"
    measured only on the frames it changed) reads as measuring every frame exactly: a 48-frame two-hand grip."""
    from retarget_core.jobs import JobInputs
    from retarget_core.metrics.frames import Reuse
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import prepare

    inputs = JobInputs(shared_data / "motions" / "cmu" / "002_08.bvh", shared_data / "characters" / "mh_male_bulky.glb",
                       options=RetargetOptions(fps=30.0, frame_end=190))  # fmt: skip
    p = prepare(inputs, max_frames=48)
    tgt, tmap, sdf = p.target.character, p.target.mapping, p.assets.sdf
    arm = tmap.joints["LeftForeArm"]
    after = _perturbed(p.before, slice(10, 30), arm, 0.6)
    hands = p.contacts.self_contacts.distances
    kw = {"contacts": p.constraints, "source_hand_distances": hands}
    full_b = measure_clip(tgt, tmap, sdf, p.before, cull_hands=False, **kw)
    full_a = measure_clip(tgt, tmap, sdf, after, cull_hands=False, **kw)
    fast_b = measure_clip(tgt, tmap, sdf, p.before, **kw)
    fast_a = measure_clip(tgt, tmap, sdf, after, reuse=Reuse(p.before, fast_b), **kw)
    assert full_b.contact_hands is not None and full_b.contact_hands.far_pairs
    assert len(full_b.contact_hands.frame) > 0, "the clip must have source hand contacts"
    for full, fast in ((full_b, fast_b), (full_a, fast_a)):
        for name in ("vertex_depth", "penetration_volume", "limb_distance", "lowest_vertex", "contact_distance"):
            torch.testing.assert_close(getattr(fast, name), getattr(full, name), atol=1e-6, rtol=1e-5)
        assert fast.contact_hands is not None and full.contact_hands is not None
        torch.testing.assert_close(fast.contact_hands.distance, full.contact_hands.distance, atol=1e-6, rtol=1e-5)
        assert fast.contact_hands.far_pairs == full.contact_hands.far_pairs
        assert fast.contact_hands.false_pairs == full.contact_hands.false_pairs
        one = summarize(fast, full_b, source_feet=p.contacts.feet).model_dump()
        other = summarize(full, full_b, source_feet=p.contacts.feet).model_dump()
        assert json.dumps(one, sort_keys=True) == json.dumps(other, sort_keys=True)
    assert not torch.equal(full_a.vertex_depth[10:30], full_b.vertex_depth[10:30]) or not torch.equal(
        full_a.lowest_vertex, full_b.lowest_vertex
    ), "the perturbation must change what is measured"


def test_hand_geometry_is_built_once_per_body() -> None:
    """"before" and "after" of a job share the body's hand-to-part geometry; another body gets its own."""
    from retarget_core.metrics.compute import cached_hand_geometry

    ch = load_preset("male_average")
    parts = body_parts(ch, mapping_by_name(ch.skeleton.names))
    other = body_parts(ch, mapping_by_name(ch.skeleton.names))
    first = cached_hand_geometry(ch, parts)
    assert cached_hand_geometry(ch, parts) is first
    fresh = cached_hand_geometry(ch, other)
    assert fresh is not first and torch.equal(fresh.faces, first.faces)


def test_false_contacts_read_at_the_false_contact_reach_as_at_the_full_reach(shared_data: Path) -> None:
    """The meter measures a pair far on the source only up to the false-contact distance: on a two-hand grip
    whose source is taken as far everywhere, its per-frame false contacts equal those of the full-reach
    distances, with pairs both nearer and farther than that distance present."""
    from dataclasses import replace

    from retarget_core.contacts.hand_distance import REFERENCE_HEIGHT_M, hand_part_distances
    from retarget_core.jobs import JobInputs
    from retarget_core.metrics.compute import FALSE_CONTACT_M, ContactHandMeter
    from retarget_core.options import RetargetOptions
    from retarget_core.pipeline import prepare

    inputs = JobInputs(shared_data / "motions" / "cmu" / "002_08.bvh", shared_data / "characters" / "mh_male_bulky.glb",
                       options=RetargetOptions(fps=30.0, frame_end=190))  # fmt: skip
    p = prepare(inputs, max_frames=48)
    body, parts = p.target.character, p.assets.sdf.parts
    posed = body.pose_vertices(*p.before.global_transforms())
    full = hand_part_distances(body, parts, posed)
    source = replace(full, distance=torch.full_like(full.distance, float("inf")))
    meter = ContactHandMeter(body, parts, None, source, frames=len(posed))
    meter.measure(posed, torch.arange(len(posed)))
    false_m = FALSE_CONTACT_M * body.height / REFERENCE_HEIGHT_M
    expected = ((full.distance < false_m) & full.measured[None]).flatten(1).sum(1)
    assert int(expected.sum()) > 0, "the grip must bring a hand within the false-contact distance of a part"
    assert bool(((full.distance >= false_m) & torch.isfinite(full.distance)).any()), "and keep pairs beyond it"
    assert torch.equal(meter.frame_false, expected)
