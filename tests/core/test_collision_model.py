"""The learned collision resolver (paper 2's per-limb model): its collision matrix reads a known depth, zero
collision gives the input back exactly, smoke training runs and saves loadable weights, the shipped weights load
and run on a sample clip (never worse per frame), and they reduce a built penetration on the bulky body."""

from __future__ import annotations

from pathlib import Path

import pytest
import roma
import torch

from retarget_core.bodies.params import BodyParams
from retarget_core.body_parts import CLUSTERS
from retarget_core.cases import context_from_prepared, prepared_case
from retarget_core.context import RefineContext
from retarget_core.geometry.judged_pairs import judged_allowed
from retarget_core.model.collision_data import build_collision_data
from retarget_core.model.collision_geometry import collision_matrix, limb_points
from retarget_core.model.collision_net import CollisionNet, body_rig, load_collision_net, pose_features, run_model
from retarget_core.model.train_collisions import CollisionTrainConfig, train_collisions
from retarget_core.motion import Motion
from retarget_core.refine import collision_model
from retarget_core.refine.collision_check import check_frames, contact_instances
from retarget_core.retargeted import Prepared
from tests.core.test_collisions import _arm_boxes, _context, _pushed_in

FRAMES = 45
ARM, TORSO = CLUSTERS.index("left_arm"), CLUSTERS.index("torso")


@pytest.fixture(scope="module")
def prepared(samples: Path) -> Prepared:
    torch.set_num_threads(1)
    return prepared_case(samples / "motions" / "007_03.bvh", samples / "characters" / "mh_male_bulky.glb", FRAMES)


@pytest.fixture(scope="module")
def ctx(prepared: Prepared) -> RefineContext:
    return context_from_prepared(prepared)


def _m_col(ctx: RefineContext, m: Motion) -> torch.Tensor:
    lp = limb_points(ctx.target, ctx.parts, ctx.sdf)
    return collision_matrix(ctx.sdf, lp, roma.unitquat_to_rotmat(m.rotations.float()), m.translations.float())


@pytest.mark.parametrize("depth", [0.02, 0.04])
def test_limb_collision_matrix_reads_a_known_depth(depth: float) -> None:
    ch = _arm_boxes()
    ctx = _context(ch, _pushed_in(ch, depth, 1))
    m = _m_col(ctx, ctx.before)
    assert m[0, ARM, TORSO] == pytest.approx(depth, abs=0.004)
    assert float(m[0].sum() - m[0, ARM, TORSO]) == pytest.approx(0.0, abs=1e-6)


def test_zero_collision_gives_the_input_back_exactly(ctx: RefineContext) -> None:
    torch.manual_seed(0)
    model = CollisionNet().eval()
    rig = body_rig(ctx.target, ctx.target_mapping, ctx.parts)
    lp = limb_points(ctx.target, ctx.parts, ctx.sdf)
    local = roma.unitquat_to_rotmat(ctx.before.rotations.float())
    _, mats, gpos = lp.poser(local, ctx.before.translations.float())
    with torch.no_grad():
        dq = run_model(model, pose_features(rig, local, mats, gpos), torch.zeros(FRAMES, 6, 6), rig.shoulder)
    assert all(bool((d == 0).all()) for d in dq.values())
    # A clip with no collision on the limbs (the rest pose) is returned unchanged by the stage.
    rest = Motion(ctx.before.skeleton, 30.0, ctx.target.skeleton.rest_rotations.expand(5, -1, -1).clone(),
                  ctx.before.translations[:5].clone(), "rest")  # fmt: skip
    out = collision_model.resolve_learned(ctx, rest, model=model)
    assert out.report["frames_changed"] == 0
    assert torch.equal(out.motion.rotations, rest.rotations)


def test_smoke_training_saves_loadable_weights(samples: Path, tmp_path: Path) -> None:
    torch.set_num_threads(1)
    body = BodyParams(name="smoke", gender=0.0, weight=0.95, muscle=0.6, height=1.62)
    data = build_collision_data([samples / "motions" / "007_03.bvh"], [body], stride=3, seed=0, max_clip_frames=60)
    assert len(data.bodies[0].rot) == 2 * 20 and data.bodies[0].m_col.shape[1:] == (6, 6)
    cfg = CollisionTrainConfig(steps=3, batch=8, bodies=1)
    log = tmp_path / "log.jsonl"
    summary = train_collisions(samples / "motions", tmp_path / "w.pt", cfg, tmp_path, log, data=data)
    assert summary["steps"] == 3 and len(log.read_text().splitlines()) == 3
    model, meta = load_collision_net(tmp_path / "w.pt")
    assert meta["config"]["batch"] == 8 and set(model.limbs) == {"left_arm", "right_arm", "left_leg", "right_leg"}


def test_shipped_weights_run_on_a_sample_clip_never_worse(ctx: RefineContext) -> None:
    assert collision_model.WEIGHTS_PATH.is_file(), "the shipped weights are missing"
    assert collision_model.WEIGHTS_PATH.stat().st_size < 2_000_000
    out = collision_model.run(ctx, ctx.before)
    rep = out.report
    assert out.motion.rotations.shape == ctx.before.rotations.shape
    assert torch.isfinite(out.motion.rotations).all()
    assert {"frames_changed", "penetration_before", "penetration_after", "model_ms_per_frame"} <= set(rep)
    # Never worse, per frame, with every vertex (what the stage itself checks).
    sdf, scale = ctx.sdf, ctx.sdf.scale_to_180
    contacts = contact_instances(sdf, ctx.constraints)
    frames = torch.arange(FRAMES)
    tol = 0.003 / scale
    b = check_frames(ctx.target, sdf, ctx.before.rotations.float(), ctx.before.translations.float(), frames, contacts, tol,
                     allowed=judged_allowed(sdf))  # fmt: skip
    a = check_frames(ctx.target, sdf, out.motion.rotations.float(), out.motion.translations.float(), frames, contacts,
                     tol, allowed=judged_allowed(sdf))  # fmt: skip
    assert bool(((a.max_depth - b.max_depth) * scale <= 0.002 + 1e-5).all())


def test_shipped_weights_reduce_a_built_penetration(ctx: RefineContext) -> None:
    """The left arm of the bulky body (T-pose on the first frame of the sample clip) turned down into its side by
    75-110 degrees about the world z axis: the shipped model must lower M_col[arm, torso] well below its depth."""
    m = ctx.before.slice(0, 1)
    j = ctx.target_mapping.joints["LeftArm"]
    grot, _ = m.global_transforms()
    parent = grot[0, m.skeleton.parents[j]].float()
    depths, motions = [], []
    for deg in range(72, 112, 4):
        r = m.rotations.clone()
        turn = roma.rotvec_to_unitquat(torch.tensor([0.0, 0.0, -deg * 3.14159 / 180.0]))
        local_turn = roma.quat_product(roma.quat_conjugation(parent), roma.quat_product(turn, parent))
        r[0, j] = roma.quat_product(local_turn, r[0, j].float()).to(r.dtype)
        cand = Motion(m.skeleton, m.fps, r, m.translations.clone(), "built")
        motions.append(cand)
        depths.append(float(_m_col(ctx, cand)[0, ARM, TORSO]))
    k = max(range(len(depths)), key=lambda i: (0.015 <= depths[i] <= 0.04, depths[i] <= 0.04, depths[i]))
    assert 0.01 <= depths[k] <= 0.05, depths
    out = collision_model.run(ctx, motions[k])
    after = float(_m_col(ctx, out.motion)[0, ARM, TORSO])
    assert after < 0.7 * depths[k], (depths[k], after, out.report)


def test_pipeline_runs_the_learned_stage_before_collisions_when_switched_on(prepared: Prepared) -> None:
    from retarget_core import pipeline
    from retarget_core.options import RetargetOptions

    opts = RetargetOptions(frame_end=FRAMES, stages={"learned_collisions": True, "foot_lock": False})
    result = pipeline.refine(prepared, options=opts)
    order = [s for s in result.stages_run if s in ("learned_collisions", "collisions")]
    assert order == ["learned_collisions", "collisions"]
    rep = result.stage_reports["learned_collisions"]
    assert rep["frames_changed"] > 0, rep  # the walk's arms are in the bulky torso: the model turns them out
    assert result.after.num_frames == prepared.before.num_frames
