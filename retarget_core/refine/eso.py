"""Refinement stage ``eso``: encoder-space optimisation of the network's states where contacts or
penetrations are not yet right (:mod:`retarget_core.model.eso`). It runs the network itself from the copy
baseline (cheap), so it needs no state from the ``recurrent`` stage; when ``recurrent`` was switched off the
result still starts from the network's output (the report says so)."""

from __future__ import annotations

import time
from dataclasses import replace

from retarget_core.context import RefineContext, StageOutcome
from retarget_core.model.energy import body_kit
from retarget_core.model.eso import ESOParams, optimise
from retarget_core.model.inference import network_inputs, run_network, shipped_network
from retarget_core.motion import Motion


def run(ctx: RefineContext, motion: Motion, params: ESOParams | None = None) -> StageOutcome:
    """ESO on the network's output for this job; report: frames optimised, contacts gated and how far each
    moved, penetration energy before and after, time per frame."""
    start = time.perf_counter()
    if params is None:
        # The job's iteration budget split over the rounds (paper: 30 steps per frame).
        base = ESOParams()
        params = replace(base, steps=max(1, ctx.options.eso_iterations // max(base.rounds, 1)))
    model = shipped_network(str(ctx.device))
    inputs = network_inputs(ctx)
    _, _, states, emb = run_network(model, inputs)
    kit = body_kit(ctx.target, ctx.target_mapping, ctx.parts, ctx.sdf)
    result = optimise(model, kit, inputs, states, emb, ctx.constraints, ctx.feet.labels, params)
    out = Motion(motion.skeleton, motion.fps, result.rotations.to(motion.rotations.dtype),
                 result.translations.to(motion.translations.dtype), motion.name)  # fmt: skip
    report = dict(result.report)
    report["frames_changed"] = report.get("frames_touched", 0) if report.get("kept") else 0
    report["started_from_network"] = True
    report["ms_per_frame"] = round(1000 * (time.perf_counter() - start) / max(motion.num_frames, 1), 3)
    return StageOutcome(out, report)


__all__ = ["run"]
