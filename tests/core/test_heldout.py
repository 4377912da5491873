"""The fixed held-out split (retarget_core.heldout, retarget_core/data/heldout.json)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from retarget_core import heldout
from retarget_core.bodies.params import PRESETS


def test_split_is_fixed_and_covers_the_cases() -> None:
    split = heldout.load_split()
    assert 8 <= len(split.clips) <= 12
    tags = {t for c in split.clips for t in c.tags}
    assert {"contact", "two-hand-grip", "walk", "bend", "torso", "legs", "head"} <= tags
    names = {b.name for b in split.bodies}
    assert {"heldout_heavy", "heldout_bulky", "heldout_short", "heldout_tall", "heldout_skinny"} == names
    assert not any(heldout.near_heldout_body(p) for p in PRESETS.values())  # presets are training/dev bodies


def test_clip_paths_and_training_exclusion(shared_data: Path) -> None:
    cmu = shared_data / "motions" / "cmu"
    held = heldout.clip_paths(cmu)
    train = heldout.training_clip_paths(cmu)
    assert len(held) == len(heldout.heldout_clip_names())
    assert not set(held) & set(train)
    assert len(held) + len(train) == len(list(cmu.glob("*.bvh")))
    assert heldout.is_heldout_clip(held[0]) and not heldout.is_heldout_clip(train[0])


def test_training_sampler_stays_away_from_heldout_bodies() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        p = heldout.sample_training_body_params(rng)
        assert min(heldout.body_distance(p, b) for b in heldout.load_split().bodies) >= heldout.EXCLUSION_RADIUS


def test_bodies_are_built_once_and_cached(tmp_path: Path) -> None:
    from retarget_core.loading import load_character

    params = heldout.load_split().bodies[2]  # short
    path = heldout.body_path(params, tmp_path)
    stamp = path.stat().st_mtime_ns
    assert heldout.body_path(params, tmp_path) == path and path.stat().st_mtime_ns == stamp
    loaded = load_character(path)
    assert abs(loaded.character.height - params.height) < 1e-3
