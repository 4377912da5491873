"""The retargeting pipeline: the only place that knows the order of the stages.

read -> copy baseline ("before") -> [later stages refine it into "after"] -> metrics -> write.
Stages not implemented in this version are reported as skipped in the metrics JSON; the result is then the
copy baseline and says so.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from retarget_core.copy_retarget import copy_retarget
from retarget_core.io.gltf_write import write_glb
from retarget_core.jobs import CancelCheck, JobCanceled, JobInputs, JobOutputs, ProgressCallback
from retarget_core.loading import LoadedCharacter, LoadedMotion, load_character, load_motion
from retarget_core.motion import Motion
from retarget_core.normalize import NormalizationReport
from retarget_core.resample import resample, select_frames

# Share of the job's time each stage takes, for the progress fraction.
STAGE_WEIGHTS: dict[str, float] = {"read": 0.25, "copy": 0.15, "metrics": 0.35, "write": 0.25}
# Stages that would refine "before" into "after"; none is in this version. (Contacts are detected and measured
# in the metrics stage, not yet enforced.)
REFINEMENT_STAGES = ("recurrent", "eso", "collisions", "foot_lock")


@dataclass
class StageClock:
    """Times stages, reports progress and honours cancellation between stages."""

    progress: ProgressCallback | None = None
    should_cancel: CancelCheck | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    done: float = 0.0

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if self.should_cancel is not None and self.should_cancel():
            raise JobCanceled(f"canceled before stage {name}")
        if self.progress is not None:
            self.progress(name, self.done)
        start = time.perf_counter()
        yield
        self.seconds[name] = round(time.perf_counter() - start, 4)
        self.done = min(1.0, self.done + STAGE_WEIGHTS.get(name, 0.0))
        if self.progress is not None:
            self.progress(name, self.done)


@dataclass
class Retargeted:
    """In-memory result of :func:`retarget`: the inputs as read, the source body with the source motion on it,
    and the before/after motions on the target."""

    source: LoadedMotion
    source_body: LoadedCharacter
    source_view: Motion
    target: LoadedCharacter
    before: Motion
    after: Motion
    stages_run: list[str]
    stages_skipped: list[str]
    warnings: list[str]


def source_body(inputs: JobInputs, source: LoadedMotion) -> LoadedCharacter:
    """The body the source motion is performed by: the one given, the motion file's own mesh, or a built-in
    body sized to the source skeleton."""
    if inputs.source_character is not None:
        return load_character(inputs.source_character)
    if source.source_character is not None:
        return source.source_character
    from retarget_core.source_body import source_body_for

    body, mapping = source_body_for(source.motion.skeleton, source.mapping)
    report = NormalizationReport(
        notes=[
            f"no source body given: a built-in body {body.height:.2f} m tall, sized to the source's bones, stands in"
        ]
    )
    return LoadedCharacter(body, mapping, report, "builtin", report.notes)


def prepare_source(inputs: JobInputs) -> LoadedMotion:
    """Read the motion and apply the frame range and frame rate of the options."""
    opts = inputs.options
    loaded = load_motion(inputs.motion_path, clip=opts.clip, fps=opts.fps, joint_map_override=opts.joint_map_override)
    motion = select_frames(loaded.motion, opts.frame_start, opts.frame_end)
    if opts.fps is not None:
        motion = resample(motion, opts.fps)
    loaded.motion = motion
    return loaded


def retarget(inputs: JobInputs, clock: StageClock | None = None) -> Retargeted:
    """Run the stages that compute motions (no files written)."""
    clock = clock or StageClock()
    opts = inputs.options
    with clock.stage("read"):
        source = prepare_source(inputs)
        target = load_character(inputs.target, joint_map_override=opts.target_joint_map_override)
        body = source_body(inputs, source)
    with clock.stage("copy"):
        before = copy_retarget(
            source.motion, source.mapping, target.character.skeleton, target.mapping, in_place=opts.in_place
        )
        source_view = copy_retarget(
            source.motion, source.mapping, body.character.skeleton, body.mapping, in_place=opts.in_place
        )
    requested = [s for s in REFINEMENT_STAGES if getattr(opts.stages, s)]
    warnings = list(source.notes) + list(target.notes) + list(body.notes)
    if requested:
        warnings.append(
            "refinement stages "
            + ", ".join(requested)
            + " are not available in this version: the result is the copy baseline"
        )
    return Retargeted(source, body, source_view, target, before, before, ["read", "copy"], requested, warnings)


def run_job(
    inputs: JobInputs,
    out_dir: Path,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> JobOutputs:
    """Retarget, measure and write ``result.glb``, ``before.glb`` and ``metrics.json`` into ``out_dir``.

    Files are written under temporary names and renamed at the end, so a failed or canceled job never leaves
    a half-written result that looks complete."""
    from retarget_core.metrics_summary import build_metrics, headline

    clock = StageClock(progress, should_cancel)
    result = retarget(inputs, clock)
    with clock.stage("metrics"):
        metrics = build_metrics(result)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {name: out_dir / name for name in ("result.glb", "before.glb", "source.glb", "metrics.json")}
    with clock.stage("write"):
        character = result.target.character
        write_glb(character, result.after, out_dir / "result.glb.part", clip_name=result.source.motion.name)
        write_glb(character, result.before, out_dir / "before.glb.part", clip_name=result.source.motion.name)
        write_glb(
            result.source_body.character,
            result.source_view,
            out_dir / "source.glb.part",
            clip_name=result.source.motion.name,
        )
        metrics["context"]["stage_seconds"] = dict(clock.seconds)
        (out_dir / "metrics.json.part").write_text(json.dumps(metrics, separators=(",", ":")))
    for name, path in paths.items():
        (out_dir / f"{name}.part").replace(path)
    if progress is not None:
        progress("done", 1.0)
    return JobOutputs(
        paths["result.glb"], paths["before.glb"], paths["metrics.json"], headline(metrics),
        dict(clock.seconds), result.warnings, paths["source.glb"],
    )  # fmt: skip
