"""Every shared clip loads and retargets onto every shared body; every result passes the glTF validator and
keeps the source's frame count and duration."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from retarget_core.copy_retarget import copy_retarget
from retarget_core.io.gltf_read import read_gltf
from retarget_core.io.gltf_write import write_glb
from retarget_core.loading import LoadedCharacter, load_character, load_motion

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gltf_validator import validate_many  # noqa: E402

pytestmark = pytest.mark.slow


def test_every_clip_onto_every_body(shared_data: Path, tmp_path: Path) -> None:
    clips = sorted((shared_data / "motions").glob("*/*.bvh"))
    bodies = sorted((shared_data / "characters").glob("*.glb"))
    assert len(clips) >= 59 and len(bodies) >= 7
    targets: list[LoadedCharacter] = [load_character(b) for b in bodies]
    written: list[Path] = []
    checked = 0
    for c, clip in enumerate(clips):
        source = load_motion(clip)
        assert source.motion.num_frames > 0
        for t, target in enumerate(targets):
            out = copy_retarget(source.motion, source.mapping, target.character.skeleton, target.mapping)
            assert out.num_frames == source.motion.num_frames
            assert abs(out.duration - source.motion.duration) < 1e-9
            assert bool(out.rotations.isfinite().all()) and bool(out.translations.isfinite().all())
            path = tmp_path / f"{clip.stem}_{bodies[t].stem}.glb"
            write_glb(target.character, out, path, clip_name=clip.stem)
            written.append(path)
        # The written clip has the source's frames and duration.
        back = read_gltf(written[-1]).motions[0]
        assert back.num_frames == source.motion.num_frames
        assert abs(back.duration - source.motion.duration) < 1e-6
        if len(written) >= 7 * 8 or c == len(clips) - 1:
            reports = validate_many(written)
            bad = {p: r for p, r in reports.items() if r["numErrors"]}
            assert not bad, f"validator errors: {bad}"
            checked += len(reports)
            for path in written:
                path.unlink()
            written = []
    assert checked == len(clips) * len(bodies)
