"""The recurrent retargeter: zero-initialised network = copy, smoke training, shipped weights on a sample
clip, and ESO lowering the energy on a built case (sample clip on the bulky sample body)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from retarget_core.bodies.params import BodyParams
from retarget_core.cases import context_from_prepared, prepared_case
from retarget_core.context import RefineContext
from retarget_core.model import inference
from retarget_core.model.data import build_dataset, draw_windows
from retarget_core.model.energy import body_kit
from retarget_core.model.eso import ESOParams, ESOResult, optimise
from retarget_core.model.features import from_6d, to_6d
from retarget_core.model.inference import NetworkInputs
from retarget_core.model.network import NetworkConfig, RecurrentRetargeter, load_network
from retarget_core.model.train_recurrent import TrainConfig, train
from retarget_core.retargeted import Prepared

FRAMES = 45


@pytest.fixture(scope="module")
def prepared(samples: Path) -> Prepared:
    torch.set_num_threads(1)
    return prepared_case(samples / "motions" / "007_03.bvh", samples / "characters" / "mh_male_bulky.glb", FRAMES)


@pytest.fixture(scope="module")
def ctx(prepared: Prepared) -> RefineContext:
    return context_from_prepared(prepared)


def test_6d_round_trip() -> None:
    q = torch.nn.functional.normalize(torch.randn(50, 4), dim=-1)
    back = from_6d(to_6d(q))
    assert torch.allclose((back * q).sum(-1).abs(), torch.ones(50), atol=1e-5)


def test_untrained_network_reproduces_the_copy(ctx: RefineContext) -> None:
    torch.manual_seed(0)
    model = RecurrentRetargeter(NetworkConfig(hidden=32, code=16)).eval()
    rot, trans, _, _ = inference.run_network(model, inference.network_inputs(ctx))
    assert torch.allclose(rot, ctx.before.rotations.float(), atol=1e-6)
    assert torch.allclose(trans, ctx.before.translations.float(), atol=1e-6)


@pytest.mark.parametrize("geometry", ["girths", "pointnet"])
def test_smoke_training_changes_the_output(samples: Path, tmp_path: Path, geometry: str) -> None:
    torch.set_num_threads(1)
    body = BodyParams(name="smoke", gender=0.0, weight=0.9, muscle=0.6, height=1.62)
    data = build_dataset([samples / "motions" / "007_03.bvh"], [body], ik_windows=1, ik_length=30, seed=0, max_clip_frames=70)
    assert {s.kind for s in data.sequences} == {"clip", "mirror", "ik"}
    batch = draw_windows(data, 0, 2, 20, np.random.default_rng(0), 0.5, (0.8, 1.25))
    assert batch.copy_rot.shape[:2] == (2, 20)
    cfg = TrainConfig(steps=3, batch=2, window=20, network=NetworkConfig(hidden=32, code=16, geometry=geometry))
    out = tmp_path / "w.pt"
    summary = train(Path("unused"), out, cfg, tmp_path, tmp_path / "log.jsonl", data=data)
    assert summary["steps"] == 3
    lines = (tmp_path / "log.jsonl").read_text().splitlines()
    assert len(lines) == 3 and all(np.isfinite(json.loads(x)["loss"]) for x in lines)
    model, meta = load_network(out)
    assert meta["steps"] == 3 and model.config.geometry == meta["config"]["network"]["geometry"] == geometry
    # Training moved the zero-initialised heads away from zero.
    assert float(model.rotation_head.weight.abs().sum()) > 0


def test_shipped_weights_retarget_a_sample_clip(ctx: RefineContext) -> None:
    from retarget_core.refine import recurrent

    assert inference.WEIGHTS_PATH.is_file(), "the shipped weights are missing"
    assert inference.WEIGHTS_PATH.stat().st_size < 5 * 2**20
    out = recurrent.run(ctx, ctx.before)
    assert out.motion.rotations.shape == ctx.before.rotations.shape
    assert torch.isfinite(out.motion.rotations).all() and torch.isfinite(out.motion.translations).all()
    assert 0 < out.report["frames_changed"] <= FRAMES  # a bulky target: the network changes the copy
    # A residual, not a new motion: joints stay within a few tens of degrees of the copy.
    assert out.report["max_joint_change_deg"] < 60


def _eso_on_built_case(ctx: RefineContext, params: ESOParams) -> tuple[ESOResult, RecurrentRetargeter, NetworkInputs]:
    """ESO with ``params`` on the built case (a small seeded network whose rotation head reads the states): its
    result, the network and the network's inputs."""
    torch.manual_seed(0)
    model = RecurrentRetargeter(NetworkConfig(hidden=32, code=16)).eval()
    # Zero heads make the output independent of the states; a built case needs heads that read them.
    torch.nn.init.normal_(model.rotation_head.weight, std=0.02)
    inputs = inference.network_inputs(ctx)
    _, _, states, emb = inference.run_network(model, inputs)
    kit = body_kit(ctx.target, ctx.target_mapping, ctx.parts, ctx.sdf)
    return optimise(model, kit, inputs, states, emb, ctx.constraints, ctx.feet.labels, params), model, inputs


def test_eso_lowers_the_energy_on_a_built_case(ctx: RefineContext, tmp_path: Path) -> None:
    result, model, inputs = _eso_on_built_case(ctx, ESOParams(rounds=1, steps=8))
    rep = result.report
    assert rep["frames_optimised"] > 0, rep
    assert rep["energy_after"] < rep["energy_before"], rep
    assert rep["kept"]
    start, _, _, _ = inference.run_network(model, inputs)
    assert bool(((result.rotations - start).abs().amax(dim=(1, 2)) > 1e-6).any())


def test_pipeline_runs_recurrent_and_eso_when_switched_on(prepared: Prepared) -> None:
    from retarget_core import pipeline
    from retarget_core.options import RetargetOptions

    opts = RetargetOptions(frame_end=FRAMES, eso_iterations=6, stages={"recurrent": True, "eso": True})
    result = pipeline.refine(prepared, options=opts)
    refining = [s for s in result.stages_run if s in ("recurrent", "eso", "collisions", "foot_lock")]
    assert refining == ["recurrent", "eso", "collisions", "foot_lock"]  # the registry's order
    assert result.stage_reports["eso"]["iterations"] == 6
    assert result.after.num_frames == prepared.before.num_frames


def test_training_keeps_out_the_heldout_split(shared_data: Path) -> None:
    from retarget_core.heldout import heldout_clip_names, near_heldout_body
    from retarget_core.model.data import training_clips
    from retarget_core.model.train_recurrent import body_bank

    clips = {p.stem for p in training_clips(shared_data / "motions" / "cmu")}
    assert clips and not clips & set(heldout_clip_names())
    assert not any(near_heldout_body(b) for b in body_bank(0, 6))


def test_ablated_energy_zeroes_its_terms() -> None:
    from retarget_core.model.train_recurrent import ENERGY_TERMS, with_energy

    full = TrainConfig()
    skeleton = with_energy(full, "skeleton")
    assert skeleton.w_contact == skeleton.w_interpenetration == skeleton.w_foot == 0.0
    assert skeleton.w_rotation == full.w_rotation and skeleton.energy == "skeleton"
    foot = with_energy(full, "foot")
    assert foot.w_foot == full.w_foot > 0 and foot.w_interpenetration == 0.0
    assert with_energy(full, "full") == full
    assert set(ENERGY_TERMS) == {"skeleton", "foot", "interpenetration", "full"}
    with pytest.raises(ValueError, match="unknown energy"):
        with_energy(full, "contact-only")


def test_network_weights_override_is_scoped(ctx: RefineContext, tmp_path: Path) -> None:
    from retarget_core.model.network import save_network

    torch.manual_seed(0)
    other = tmp_path / "zero.pt"
    save_network(RecurrentRetargeter(NetworkConfig(hidden=32, code=16)).eval(), other, {"steps": 0})
    shipped = inference.shipped_network()
    with inference.network_weights(other):
        inside = inference.shipped_network()
    assert inside is not shipped and inside.config.hidden == 32
    assert inference.shipped_network() is shipped


def test_pointnet_network_reproduces_the_copy_and_round_trips(ctx: RefineContext, tmp_path: Path) -> None:
    from retarget_core.model.features import POINT_DIM, POINTS
    from retarget_core.model.network import save_network

    torch.manual_seed(0)
    config = NetworkConfig(hidden=32, code=16, geometry="pointnet", point_hidden=16, point_code=8)
    model = RecurrentRetargeter(config).eval()
    inputs = inference.network_inputs(ctx)
    assert inputs.points is not None and inputs.points.shape == (1, POINTS, POINT_DIM)
    rot, trans, _, emb = inference.run_network(model, inputs)
    assert torch.allclose(rot, ctx.before.rotations.float(), atol=1e-6)
    assert torch.allclose(trans, ctx.before.translations.float(), atol=1e-6)
    # The embedding reads the points: other points, another embedding.
    other = model.embed(inputs.code, inputs.points * 1.1)
    assert not torch.allclose(emb, other)
    with pytest.raises(ValueError, match="geometry points"):
        model.embed(inputs.code)
    path = tmp_path / "pointnet.pt"
    save_network(model, path, {"steps": 0})
    back, _ = load_network(path)
    assert back.config == config and back.pointnet is not None
    assert torch.equal(back.embed(inputs.code, inputs.points), emb)


def test_geometry_points_are_seeded_and_fill_small_meshes() -> None:
    from retarget_core.model.features import point_sample

    assert torch.equal(point_sample(5000, 64), point_sample(5000, 64))
    small = point_sample(10, 25)
    assert small.shape == (25,) and set(small.tolist()) == set(range(10))
    with pytest.raises(ValueError, match="unknown geometry"):
        NetworkConfig(geometry="voxels")


def _third_difference(x: torch.Tensor) -> torch.Tensor:
    return x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]


def test_eso_offsets_change_without_kinks() -> None:
    """ESO's state offsets live on knots every 6 frames: a partition of unity, and a curve through them whose
    third differences (the judge's jerk) stay well under those of straight lines between the same points (issue
    22 item 4: jerk 1.15 on a production character)."""
    from retarget_core.model.eso import _knot_weights

    torch.manual_seed(0)
    interp = _knot_weights(60, 6)
    assert torch.allclose(interp.sum(dim=1), torch.ones(60))
    knots = torch.randn(interp.shape[1])
    spline = interp @ knots
    straight = torch.from_numpy(np.interp(np.arange(60), np.arange(0, 60, 6), (interp[::6] @ knots).numpy()))
    assert float(_third_difference(spline).abs().max()) < 0.5 * float(_third_difference(straight).abs().max())


def test_eso_change_is_smoother_with_its_jerk_term(ctx: RefineContext) -> None:
    """On the built case of :func:`test_eso_lowers_the_energy_on_a_built_case` (default rounds and steps), ESO's
    change (joint positions, result minus the network's) has less jerk with its smoothness term than without."""
    from retarget_core.kinematics import forward_kinematics

    def change_jerk(w_smooth: float) -> float:
        result, model, inputs = _eso_on_built_case(ctx, ESOParams(w_smooth=w_smooth))
        start_rot, start_trans, _, _ = inference.run_network(model, inputs)
        parents = ctx.target.skeleton.parents
        moved = forward_kinematics(parents, result.rotations, result.translations)[1]
        shape_r, shape_t = result.rotations.shape, result.translations.shape
        start = forward_kinematics(parents, start_rot.reshape(shape_r), start_trans.reshape(shape_t))[1]
        return float(_third_difference(moved - start).norm(dim=-1).mean())

    with_term, without = change_jerk(ESOParams().w_smooth), change_jerk(0.0)
    assert with_term < 0.95 * without  # 0.92 x here, a small change; the Witch's 002_01: ESO's jerk 1.13 -> 1.09
