"""The hard held-out split (retarget_core.heldout_hard, retarget_core/data/heldout_hard.json) and the case-list
evaluation it runs on."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from retarget_core import heldout, heldout_hard
from retarget_core.evaluation import EvalTable

HARD_KINDS = ("self-wash", "folded-arms", "two-hand-grip", "dance")
HEAVIEST = {"hard_heaviest", "heldout_heavy", "heldout_bulky"}


def test_split_file_invariants() -> None:
    split = heldout_hard.load_hard_split()
    names = [c.name for c in split.clips]
    assert len(names) >= 20 and len(set(names)) == len(names)
    assert {b.name for b in heldout.load_split().bodies} <= {b.name for b in split.bodies}
    assert {"hard_heaviest", "hard_shortest"} <= {b.name for b in split.bodies}
    assert len(split.real_characters) >= 2
    bodies = split.body_names()
    assert len(set(bodies)) == len(bodies)
    assert all(c in names and b in bodies for c, b in split.cases)  # every case's clip and body is defined
    assert len(set(split.cases)) == len(split.cases)
    assert set(names) == {c for c, _ in split.cases} and set(bodies) == {b for _, b in split.cases}
    assert split.max_frames == 300


def test_no_training_clip_in_the_split() -> None:
    split = heldout_hard.load_hard_split()
    for clip in split.clips:
        folder = Path(clip.file).parent.name
        assert folder in ("cmu", "cmu_hard"), clip.file
        if folder == "cmu":  # the training folder: only its held-out clips may be used
            assert heldout.is_heldout_clip(clip.file), clip.name


def test_hard_kinds_hit_the_heaviest_bodies() -> None:
    split = heldout_hard.load_hard_split()
    tags = {c.name: c.tags for c in split.clips}
    assert all(any(k in t for t in tags.values()) for k in HARD_KINDS)
    for clip, _ in split.cases:
        if any(k in tags[clip] for k in HARD_KINDS):
            on = {b for c, b in split.cases if c == clip}
            assert len(on & HEAVIEST) >= 2, (clip, on)
    per_body = Counter(b for _, b in split.cases)
    assert max(per_body.values()) - min(per_body.values()) <= 1, per_body
    for real in split.real_characters:
        assert any(any(k in tags[c] for k in HARD_KINDS) for c, b in split.cases if b == real.name), real.name


def test_heaviest_and_shortest_bodies_are_extreme() -> None:
    split = heldout_hard.load_hard_split()
    params = {b.name: b for b in split.bodies}
    assert params["hard_heaviest"].weight == 1.0 and params["hard_heaviest"].muscle == 1.0
    heights = [b.height for b in split.bodies if b.height is not None]
    assert params["hard_shortest"].height == min(heights)


def test_group_cases_keeps_the_order_and_refuses_repeats() -> None:
    from retarget_core.evaluation import group_cases

    a, b = Path("a.bvh"), Path("b.bvh")
    assert group_cases([(a, "x"), (b, "y"), (a, "z")]) == [(a, ["x", "z"]), (b, ["y"])]
    with pytest.raises(ValueError, match="twice"):
        group_cases([(a, "x"), (a, "x")])


def test_split_cases_keeps_only_the_named_cases(shared_data: Path) -> None:
    split = heldout_hard.load_hard_split()
    cases = heldout_hard.split_cases(shared_data, split, only=["002_08"])  # a shared clip on generated bodies
    expected = [(c, b) for c, b in split.cases if c == "002_08"]
    assert len(expected) == 3
    assert [(p.stem, q.stem.split("-")[0]) for p, q in cases] == expected
    with pytest.raises(ValueError, match="no case"):
        heldout_hard.split_cases(shared_data, split, only=["no-such-clip"])


def _real_character_or_skip(shared_data: Path, name: str, split: heldout_hard.HardSplit) -> Path:
    """The fetched character's file; skips where the shared data lacks it (it is not in a plain checkout)."""
    try:
        return heldout_hard.body_file(shared_data, name, split)
    except FileNotFoundError as err:  # fetched characters live only in the shared data (rigs/README.md)
        pytest.skip(f"{err}: see retarget_core/data/samples/rigs/README.md")


def _evaluate_two_cases(shared_data: Path, tmp_path: Path, first_body: Path) -> EvalTable:
    """Runs a 2-case list (first_body, then heldout_skinny) on two held-out clips of the shared set, 6 frames."""
    from retarget_core.evaluation import run_evaluation

    split = heldout_hard.load_hard_split()
    skinny = heldout_hard.body_file(shared_data, "heldout_skinny", split)
    clip = heldout_hard.clip_file(shared_data, next(c for c in split.clips if c.name == "002_08"))
    other = heldout_hard.clip_file(shared_data, next(c for c in split.clips if c.name == "007_01"))
    table = run_evaluation([], [], methods=["full"], out_dir=tmp_path, max_frames=6, log=None,
                           source_glb_body=heldout.SOURCE_BODY, cases=[(clip, first_body), (other, skinny)],
                           body_groups=heldout_hard.body_groups(shared_data, split))  # fmt: skip
    assert [(r.method, r.clip, r.body) for r in table.rows] == [
        ("copy", "002_08", first_body.stem), ("full", "002_08", first_body.stem),
        ("copy", "007_01", skinny.stem), ("full", "007_01", skinny.stem),
    ]  # fmt: skip
    md = (tmp_path / "eval.md").read_text()
    assert "## Every case" in md and f"| full | 002_08 | {first_body.stem} |" in md
    assert table.settings["cases"] == 2
    return table


def test_case_list_evaluation_smoke(shared_data: Path, tmp_path: Path) -> None:
    heavy = heldout_hard.body_file(shared_data, "hard_heaviest")
    table = _evaluate_two_cases(shared_data, tmp_path, heavy)
    assert {b.group for b in table.bodies} == {"makehuman"}


def test_case_list_evaluation_groups_a_real_character(shared_data: Path, tmp_path: Path) -> None:
    witch = _real_character_or_skip(shared_data, "witch", heldout_hard.load_hard_split())
    table = _evaluate_two_cases(shared_data, tmp_path, witch)
    assert {b.group for b in table.bodies} == {"real", "makehuman"}
