"""One clip x body as the held-out evaluation runs it, for the diagnostics (chain_diag, feet_diag,
collision_diag): the clip written as a GLB on a source body (what a studio sends), the job prepared on the
target from it, and the judge's measures of that source file.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import dataclass
from pathlib import Path

from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.evaluation import judged_source, method_options, source_as_glb
from retarget_core.jobs import JobInputs
from retarget_core.metrics.acceptance import ClipAcceptance, measure_acceptance
from retarget_core.pipeline import prepare
from retarget_core.retargeted import Prepared

JUDGE_FPS = 30.0  # what `retarget eval` resamples every clip to


def case_parser(description: str | None, frames: int = 100) -> argparse.ArgumentParser:
    """The diagnostics' common arguments: clip, body, ``--frames``, ``--source-body``, ``--json``."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clip", type=Path)
    ap.add_argument("body")
    ap.add_argument("--frames", type=int, default=frames)
    ap.add_argument("--source-body", default="builtin:male_average")
    ap.add_argument("--json", type=Path, default=None)
    return ap


@dataclass
class HeldoutCase:
    """prepared: the job on the target; source: the judge's measures of the source file, performed by
    ``source_character`` (with ``source_mapping``)."""

    prepared: Prepared
    source: ClipAcceptance
    source_character: Character
    source_mapping: JointMapping


def prepare_case(clip: Path, body: str, frames: int, source_body: str, method: str = "full") -> HeldoutCase:
    """``clip`` (its first ``frames`` frames at 30 fps) sent as a GLB on ``source_body`` and prepared on ``body``
    with ``method``'s options (see :func:`retarget_core.evaluation.method_options`)."""
    with tempfile.TemporaryDirectory(prefix="heldout-case-") as tmp:
        glb = source_as_glb(clip, source_body, Path(tmp) / f"{clip.stem}.glb", frames, JUDGE_FPS)
        prepared = prepare(JobInputs(glb, body, None, method_options(method, JUDGE_FPS)), max_frames=frames)
        judged = judged_source(glb, prepared)
    if judged is None:
        raise ValueError(f"{clip}: the source GLB could not be read back with its body")
    character, mapping, motion = judged
    return HeldoutCase(prepared, measure_acceptance(character, mapping, motion), character, mapping)
