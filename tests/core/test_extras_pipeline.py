"""Extra joints through the whole job: a real MakeHuman body on the Mixamo rig (fingers curling) retargeted onto
another on the Unreal-style rig: every refinement stage of the default chain but the finger clearance keeps the
copy's finger rotations (that stage turns a finger sunk into the body, as it turns one on this walk since ESO's
change became smoother: tests/core/test_fingers_on_thigh.py), and the result GLB animates the fingers and passes
the Khronos validator."""

from __future__ import annotations

from pathlib import Path

import pygltflib
import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.copy_retarget import copy_retarget
from retarget_core.io.gltf_write import write_glb
from retarget_core.jobs import JobInputs
from retarget_core.loading import load_motion
from retarget_core.mapping import map_joints
from retarget_core.motion import Motion
from retarget_core.options import RetargetOptions
from retarget_core.pipeline import prepare, refine, write_outputs
from tests import gltf_validator
from tests.core.extras_rigs import about, finger_axis, finger_body

FRAMES = 24


def _curl(motion: Motion, mapping, frames: int) -> Motion:  # type: ignore[no-untyped-def]
    """``motion`` with every finger joint curling 0 -> 70 -> 0 degrees about its hand's knuckle line."""
    sk = motion.skeleton
    grot, _ = sk.rest_global()
    local = motion.rotations.clone()
    angle = torch.deg2rad(70 * torch.sin(torch.linspace(0, torch.pi, frames)))
    for side in ("Left", "Right"):
        axis = finger_axis(sk, mapping, side)
        for name, j in mapping.extras.items():
            if name.startswith(side + "Hand"):
                turn = about(rot.apply(rot.inv(grot[j]), axis), angle)
                local[:, j] = rot.normalize(rot.mul(local[:, j], turn))
    return Motion(sk, motion.fps, local, motion.translations, motion.name)


@pytest.fixture(scope="module")
def finger_job(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple:  # type: ignore[type-arg]
    tmp = tmp_path_factory.mktemp("fingers")
    source_char = finger_body("female_skinny", "mixamo")
    smap = map_joints(source_char.skeleton)
    clip = load_motion(samples / "motions" / "007_03.bvh")
    walk = copy_retarget(clip.motion, clip.mapping, source_char.skeleton, smap)
    walk = Motion(walk.skeleton, walk.fps, walk.rotations[:FRAMES], walk.translations[:FRAMES], "walk")
    write_glb(source_char, _curl(walk, smap, FRAMES), tmp / "source.glb", clip_name="walk")
    write_glb(finger_body("male_bulky", "game_engine"), None, tmp / "target.glb")
    inputs = JobInputs(tmp / "source.glb", tmp / "target.glb", options=RetargetOptions(stages={"fingers": False}))
    prepared = prepare(inputs)
    return prepared, refine(prepared), tmp


def test_refinement_keeps_the_copy_finger_rotations(finger_job: tuple) -> None:  # type: ignore[type-arg]
    prepared, result, _ = finger_job
    tmap = prepared.target.mapping
    fingers = [j for n, j in tmap.extras.items() if "Hand" in n]
    assert len(fingers) == 30 and set(result.stages_run) >= {"collisions", "foot_lock"}
    before = prepared.before.rotations[:, fingers]
    assert float(_angle(before[0], before[FRAMES // 2]).max()) > 30.0  # the copy curls them
    assert torch.allclose(result.after.rotations[:, fingers], before, atol=1e-6)


def test_result_glb_animates_the_fingers(finger_job: tuple) -> None:  # type: ignore[type-arg]
    prepared, result, tmp = finger_job
    from retarget_core.metrics_summary import build_metrics

    paths = write_outputs(result, tmp / "out", build_metrics(result))
    gltf_validator.assert_valid_glb(paths["result_glb"])
    g = pygltflib.GLTF2().load(str(paths["result_glb"]))
    anim = g.animations[0]
    keyed = {g.nodes[c.target.node].name: g.accessors[anim.samplers[c.sampler].input].count for c in anim.channels
             if c.target.path == "rotation"}  # fmt: skip
    names = prepared.target.character.skeleton.names
    assert all(keyed.get(names[j]) == FRAMES for n, j in prepared.target.mapping.extras.items() if "Hand" in n)
    assert len(anim.channels) < 2 * len(names)  # joints the source does not drive are not keyed every frame


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    d = rot.mul(rot.inv(a), b)
    return torch.rad2deg(2 * torch.atan2(d[..., :3].norm(dim=-1), d[..., 3].abs()))
