"""The retargeting pipeline: the only place that knows the order of the stages.

    read -> copy onto the source body -> contacts -> copy baseline ("before", placed by its mesh) -> body
         -> refinement stages (retarget_core.refine, in the order of retarget_core.stages) -> metrics -> write

:func:`prepare` runs everything up to "before", :func:`refine` the refinement stages on it, :func:`retarget`
both, :func:`run_job` all of it with the files written. The CLI, the worker and ``retarget eval`` all call
these; none rebuilds the sequence.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from torch import Tensor

from retarget_core.body_cache import body_assets
from retarget_core.contacts.foot_contact import FOOT_JOINTS, FootContacts
from retarget_core.copy_retarget import copy_retarget
from retarget_core.extras import refresh_twists, transfer_notes
from retarget_core.io.gltf_write import write_glb
from retarget_core.jobs import OUTPUT_FILES, CancelCheck, JobCanceled, JobInputs, JobOutputs, ProgressCallback
from retarget_core.loading import LoadedCharacter, LoadedMotion, load_character, load_motion
from retarget_core.measure import SourceContactResult, carry_contacts, detect_source_contacts, torch_threads
from retarget_core.memory import release_free_memory
from retarget_core.metrics.feet_acceptance import toe_heights
from retarget_core.metrics_summary import build_metrics, headline
from retarget_core.motion import Motion
from retarget_core.normalize import NormalizationReport
from retarget_core.options import RetargetOptions
from retarget_core.placement import before_labels, place_on_floor, planted_as_judged, stand_on_own_feet
from retarget_core.refine import RefineContext, refinement_stages, resolve_device
from retarget_core.resample import resample, select_frames
from retarget_core.retargeted import Prepared, Retargeted
from retarget_core.stages import PREPARE_ORDER, progress_weight

PIPELINE_THREADS = 1
"""Torch intra-op threads while a job runs: the stages are many small tensor operations, for which OpenMP's
parallel regions cost more than they save on a small shared CPU (benchmarks/bench/results/metrics_benchmark*.json)."""


@dataclass
class StageClock:
    """Times stages, reports progress (overall and within a stage) and honours cancellation between stages."""

    progress: ProgressCallback | None = None
    should_cancel: CancelCheck | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    done: float = 0.0

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if self.should_cancel is not None and self.should_cancel():
            raise JobCanceled(f"canceled before stage {name}")
        self._tell(name, self.done)
        start = time.perf_counter()
        yield
        release_free_memory()  # a stage's freed arrays go back to the system, not on top of the next one's
        self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - start, 4)
        self.done = min(1.0, self.done + progress_weight(name))
        self._tell(name, self.done)

    def within(self, name: str) -> Any:
        """A callback ``(fraction of stage name done) -> None`` for long stages."""
        return lambda fraction: self._tell(name, min(1.0, self.done + progress_weight(name) * fraction))

    def _tell(self, name: str, fraction: float) -> None:
        if self.progress is not None:
            self.progress(name, fraction)


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


def prepare_source(inputs: JobInputs, max_frames: int | None = None, skip_frames: int = 0) -> LoadedMotion:
    """Read the motion and apply the options' frame range, then their frame rate, then the window of
    ``max_frames`` frames from ``skip_frames`` on after resampling (the evaluation and scripts use it)."""
    opts = inputs.options
    loaded = load_motion(inputs.motion_path, clip=opts.clip, fps=opts.fps, joint_map_override=opts.joint_map_override)
    motion = select_frames(loaded.motion, opts.frame_start, opts.frame_end)
    if opts.fps is not None:
        motion = resample(motion, opts.fps)
    if max_frames is not None or skip_frames:
        motion = select_frames(motion, skip_frames, None if max_frames is None else skip_frames + max_frames)
    loaded.motion = motion
    return loaded


def _as_in_file(source: LoadedMotion, body: LoadedCharacter, view: Motion) -> Motion:
    """``view`` (the source on its body, placed on its own feet) at the height it has in the source file, when the
    file carries the body (glTF/GLB/FBX): the judge reads a source file in its own coordinates, and a foot 4 cm
    above the file's floor is not planted for it. BVH sources (no body in the file) are left as they stand."""
    if body is not source.source_character or view.num_frames != source.motion.num_frames:
        return view
    root = [j for j, p in enumerate(view.skeleton.parents) if p < 0]  # a root's position is its translation
    lift = float((source.motion.translations[:, root[0], 1] - view.translations[:, root[0], 1]).mean())
    lift += source.normalization.ground_m
    t = view.translations.clone()
    t[:, root, 1] += lift
    return replace(view, translations=t)


def _no_self_contacts(found: SourceContactResult) -> SourceContactResult:
    """``found`` without its hand contacts (the contacts stage switched off; the feet stay)."""
    sc = found.self_contacts
    per_contact = {f.name: getattr(sc, f.name)[:0] for f in fields(sc)
                   if isinstance(getattr(sc, f.name), Tensor) and getattr(sc, f.name).shape[:1] == (sc.count,)}  # fmt: skip
    return SourceContactResult(replace(sc, **per_contact), found.feet, found.body_name)


def prepare(
    inputs: JobInputs, clock: StageClock | None = None, *, max_frames: int | None = None, skip_frames: int = 0
) -> Prepared:
    """Read, find the contacts on the source and make the copy baseline ("before") on the target
    (``max_frames``/``skip_frames``: see :func:`prepare_source`)."""
    clock = clock or StageClock()
    opts = inputs.options
    with clock.stage("read"):
        source = prepare_source(inputs, max_frames, skip_frames)
        target = load_character(inputs.target, joint_map_override=opts.target_joint_map_override)
        body = source_body(inputs, source)
    with clock.stage("copy"):
        source_view = copy_retarget(
            source.motion, source.mapping, body.character.skeleton, body.mapping, in_place=opts.in_place
        )
        source_view = stand_on_own_feet(body.character, body.mapping, source_view)
    with clock.stage("contacts"):
        found = detect_source_contacts(body.character, body.mapping, source_view)
        if not opts.stages.enabled("contacts"):
            found = _no_self_contacts(found)
        constraints = carry_contacts(found.self_contacts, body.character, body.mapping, target.character, target.mapping)
        target_feet = FootContacts(found.feet.labels, [target.mapping.joints.get(c, -1) for _, c in FOOT_JOINTS])
        as_judged = _as_in_file(source, body, source_view)
        source_planted = planted_as_judged(body.character, body.mapping, as_judged)
        source_toe_heights = toe_heights(body.character, body.mapping, as_judged)
    with clock.stage("copy"):
        before = copy_retarget(
            source.motion, source.mapping, target.character.skeleton, target.mapping, in_place=opts.in_place
        )
        before = place_on_floor(target.character, target.mapping, before, before_labels(source_planted, found.feet))
    with clock.stage("body"):
        assets, cached = body_assets(target.character, target.mapping)
    warnings = list(source.notes) + list(target.notes) + list(body.notes)
    warnings += transfer_notes(source.mapping, target.mapping)
    return Prepared(inputs, source, body, target, source_view, found, constraints, target_feet, before, assets,
                    warnings, cached, source_planted, source_toe_heights)  # fmt: skip


def refine_context(prepared: Prepared, options: RetargetOptions | None = None) -> RefineContext:
    """What the refinement stages read, from the prepared job (``options``: default the job's)."""
    opts = options or prepared.inputs.options
    return RefineContext(
        target=prepared.target.character, target_mapping=prepared.target.mapping,
        parts=prepared.assets.parts, sdf=prepared.assets.sdf,
        source_body=prepared.source_body.character, source_mapping=prepared.source_body.mapping,
        source_view=prepared.source_view, self_contacts=prepared.contacts.self_contacts,
        constraints=prepared.constraints, feet=prepared.target_feet, planted=prepared.source_planted,
        toe_heights=prepared.source_toe_heights,
        before=prepared.before, options=opts, device=resolve_device(opts.device),
    )  # fmt: skip


def refine(prepared: Prepared, clock: StageClock | None = None, options: RetargetOptions | None = None) -> Retargeted:
    """Run the refinement stages switched on in ``options`` (default: the job's) on "before"."""
    clock = clock or StageClock()
    opts = options or prepared.inputs.options
    ctx = refine_context(prepared, opts)
    warnings = list(prepared.warnings)
    if ctx.device.type != opts.device.split(":")[0] and opts.device != "auto":
        warnings.append(f"device {opts.device!r} is not available here: the job ran on the CPU")
    motion = prepared.before
    run, skipped, reports = list(PREPARE_ORDER), [], {}
    for info, stage in refinement_stages():
        if not opts.stages.enabled(info.name):
            continue
        if stage is None:
            skipped.append(info.name)
            continue
        ctx.progress = clock.within(info.name)
        with clock.stage(info.name):
            outcome = stage(ctx, motion)
        motion = outcome.motion
        reports[info.name] = {**outcome.report, "seconds": clock.seconds[info.name]}
        run.append(info.name)
    if motion is not prepared.before:
        motion = refresh_twists(motion, prepared.target.mapping)  # twist bones follow the limbs the stages turned
    if skipped:
        warnings.append(f"stages {', '.join(skipped)} are not available in this version and were skipped")
    if motion is prepared.before:
        warnings.append("no refinement stage ran: the result is the copy baseline")
    return Retargeted(prepared, motion, run, skipped, reports, warnings)


def retarget(inputs: JobInputs, clock: StageClock | None = None) -> Retargeted:
    """Every stage that computes motions (no files written)."""
    clock = clock or StageClock()
    with torch_threads(PIPELINE_THREADS):
        return refine(prepare(inputs, clock), clock)


def write_outputs(result: Retargeted, out_dir: Path, metrics: dict[str, Any]) -> dict[str, Path]:
    """The job's files (:data:`retarget_core.jobs.OUTPUT_FILES`) in ``out_dir``, written under temporary names
    and renamed at the end, so a failed or canceled job never leaves a half-written result that looks complete."""
    out_dir.mkdir(parents=True, exist_ok=True)
    clip = result.source.motion.name
    character = result.target.character
    parts = {key: out_dir / f"{name}.part" for key, name in OUTPUT_FILES.items()}
    write_glb(character, result.after, parts["result_glb"], clip_name=clip)
    write_glb(character, result.before, parts["before_glb"], clip_name=clip)
    write_glb(result.source_body.character, result.source_view, parts["source_glb"], clip_name=clip)
    parts["metrics_json"].write_text(json.dumps(metrics, separators=(",", ":")))
    paths = {key: out_dir / name for key, name in OUTPUT_FILES.items()}
    for key, tmp in parts.items():
        tmp.replace(paths[key])
    return paths


def run_job(
    inputs: JobInputs,
    out_dir: Path,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> JobOutputs:
    """Retarget, measure and write the job's files (:data:`retarget_core.jobs.OUTPUT_FILES`) into ``out_dir``."""
    clock = StageClock(progress, should_cancel)
    with torch_threads(PIPELINE_THREADS):
        result = refine(prepare(inputs, clock), clock)
        with clock.stage("metrics"):
            metrics = build_metrics(result)
    with clock.stage("write"):
        metrics["context"]["stage_seconds"] = dict(clock.seconds)
        paths = write_outputs(result, out_dir, metrics)
    metrics["context"]["stage_seconds"] = dict(clock.seconds)
    if progress is not None:
        progress("done", 1.0)
    return JobOutputs(paths["result_glb"], paths["before_glb"], paths["metrics_json"], headline(metrics),
                      dict(clock.seconds), result.warnings, paths["source_glb"])  # fmt: skip


__all__ = ["StageClock", "prepare", "prepare_source", "refine", "refine_context", "retarget", "run_job", "source_body", "write_outputs"]
