"""Why a frame is deeper than 1 cm (issue 22, item 3): the metrics name each deep frame's cause."""

from __future__ import annotations

import math

import pytest
import torch

from retarget_core import kinematics
from retarget_core.bodies import load_preset
from retarget_core.body_parts import CLUSTERS, body_parts, mapping_by_name
from retarget_core.energy.sdf import build_part_sdf, segment_matrices
from retarget_core.metrics.compute import measure_clip, summarize
from retarget_core.metrics.deep_frames import (
    CAUSES,
    HELD_SEGMENTS,
    LIMB_LINES,
    _least_turned_depth,
    _line_distance,
    _posed_at,
    _turned,
)
from retarget_core.motion import Motion
from tests.core.test_metrics import arm_swung


@pytest.fixture(scope="module")
def average_body():  # type: ignore[no-untyped-def]
    ch = load_preset("male_average")
    mapping = mapping_by_name(ch.skeleton.names)
    return ch, mapping, build_part_sdf(ch, body_parts(ch, mapping))


def test_a_turn_keeps_the_distance_from_the_line() -> None:
    """Rodrigues' turn: the same distance from the axis, a quarter turn of x about z is y, no turn is the point."""
    v = torch.tensor([[1.0, 0.0, 0.0], [0.3, -0.2, 0.9]], dtype=torch.float64)
    axis = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]], dtype=torch.float64)
    angles = torch.tensor([0.0, math.pi / 2, 1.0], dtype=torch.float64)
    out = _turned(v, axis, angles)
    assert out[0, 1].tolist() == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)
    assert torch.allclose(out[:, 0], v)
    before = _line_distance(v, axis)
    for t in range(3):
        assert _line_distance(out[:, t], axis).tolist() == pytest.approx(before.tolist())


def test_deep_frames_are_counted_and_split_by_cause(average_body) -> None:  # type: ignore[no-untyped-def]
    """The rest pose is not deep; each arm swung through the torso is. The summary's share is the frames whose
    deepest vertex passes 1 cm, the causes add up to it and the series names each deep frame's cause. "placement"
    is a sure claim: read over every turnable vertex of the limb (not the stage's sample), no turn of the elbow
    about the shoulder-wrist line up to the largest brings the arm under 1 cm; the right arm is such a frame."""
    ch, mapping, sdf = average_body
    poses = [ch.skeleton.rest_global(), arm_swung(ch, mapping, "Left", -60.0), arm_swung(ch, mapping, "Right", 60.0)]
    grot = torch.stack([g for g, _ in poses])
    gpos = torch.stack([p for _, p in poses])
    lr, lt = kinematics.global_to_local(ch.skeleton.parents, grot, gpos)
    measures = measure_clip(ch, mapping, sdf, Motion(ch.skeleton, 30.0, lr, lt, "arms_in"))
    out = summarize(measures)
    deepest = out.series["penetration_max_depth"].values
    assert deepest[0] == 0.0 and deepest[1] > 1.0 and deepest[2] > 1.0
    assert out.summary.deep_frames_percent == pytest.approx(200.0 / 3, abs=1e-3)
    split = out.summary.deep_frames_percent_by_cause
    assert split is not None and list(split) == list(CAUSES)
    assert sum(split.values()) == pytest.approx(out.summary.deep_frames_percent, abs=1e-3)
    cause = out.series["deep_frame_cause"].values
    assert cause[0] is None and cause[2] == CAUSES.index("placement") and cause[1] in (0, 1)
    frame, vertex, _, _ = measures.depths.deepest(0.01 * ch.height / 1.8, 1)
    for f, v, side in zip(frame.tolist(), vertex.tolist(), ("left", "right"), strict=True):
        if cause[f] == CAUSES.index("placement"):
            assert _every_turn_floor(ch, mapping, sdf, grot[f], gpos[f], v, side) > 0.01 * ch.height / 1.8


def test_deep_frames_read_in_chunks_give_the_same_causes(average_body, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Deep frames read one at a time (a long clip's chunks) name the same causes as read together."""
    from retarget_core.metrics import deep_frames as module

    ch, mapping, sdf = average_body
    poses = [arm_swung(ch, mapping, side, deg) for side, deg in (("Left", -60.0), ("Right", 60.0), ("Left", -45.0))]
    grot = torch.stack([g for g, _ in poses])
    gpos = torch.stack([p for _, p in poses])
    lr, lt = kinematics.global_to_local(ch.skeleton.parents, grot, gpos)
    motion = Motion(ch.skeleton, 30.0, lr, lt, "arms_in")
    together = measure_clip(ch, mapping, sdf, motion).deep
    monkeypatch.setattr(module, "CHUNK", 1)
    apart = measure_clip(ch, mapping, sdf, motion).deep
    assert together is not None and apart is not None and together.cause is not None and apart.cause is not None
    assert bool(together.deep.all()) and torch.equal(together.cause, apart.cause)


def _every_turn_floor(ch, mapping, sdf, grot, gpos, vertex: int, side: str) -> float:  # type: ignore[no-untyped-def]
    """The floor of :func:`_least_turned_depth` read over every vertex of the arm that turns, at one frame."""
    parts = sdf.parts
    limb = CLUSTERS.index(f"{side}_arm")
    turns = torch.tensor([parts.cluster[s] == limb and parts.names[s] not in HELD_SEGMENTS
                          for s in range(parts.num_parts)])  # fmt: skip
    rows = torch.cat([torch.tensor([vertex]), torch.nonzero(turns[parts.vertex_part]).flatten()])[None]
    at = _posed_at(ch, rows, grot[None], gpos[None])
    root, end = LIMB_LINES[f"{side}_arm"]
    a, b = gpos[None, mapping.joints[root]].double(), gpos[None, mapping.joints[end]].double()
    mats = segment_matrices(ch, parts, grot[None], gpos[None]).double()
    return float(_least_turned_depth(sdf, rows, at, a, b, mats, limb)[0])
