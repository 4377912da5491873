"""Measuring one job: contacts on the source, carried to the target, and the metrics of "before" and "after".

- :func:`detect_source_contacts`: hand self-contacts and foot contacts of the source motion on its body.
- :func:`carry_contacts`: the source's hand contacts as vertex-pair constraints on the target.
- :func:`measure_job`: the metrics report of one motion x target from the motions the pipeline made (the
  source on its body, "before" and optionally "after" on the target).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch

from retarget_core.body_cache import body_assets
from retarget_core.body_parts import body_parts
from retarget_core.canonical import JointMapping
from retarget_core.character import Character
from retarget_core.contacts.correspondence import (
    ContactConstraints,
    build_correspondence,
    no_contacts,
    transfer_contacts,
)
from retarget_core.contacts.foot_contact import FootContacts, detect_foot_contacts
from retarget_core.contacts.self_contact import SelfContacts, detect_self_contacts
from retarget_core.metrics.compute import ClipMeasures, compute_metrics, summarize
from retarget_core.metrics.frames import Reuse
from retarget_core.metrics.report import (
    ContactVertexPairs,
    MetricsReport,
    SelfContactEntry,
    SourceContacts,
    build_metrics_report,
)
from retarget_core.metrics.source import measure_source
from retarget_core.motion import Motion

MEASURE_THREADS = 1
"""Torch intra-op threads while measuring: the queries are many small tensor operations, and on a small, shared
CPU OpenMP's parallel regions cost more than they save (``benchmarks/bench/metrics_benchmark.py --threads N``)."""


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (None: leave as is), restoring the setting after."""
    if n is None or n == torch.get_num_threads():
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@dataclass
class SourceContactResult:
    """Contacts found on the source: hand self-contacts (on the source body's vertices) and foot contacts."""

    self_contacts: SelfContacts
    feet: FootContacts
    body_name: str


def detect_source_contacts(body: Character, mapping: JointMapping, motion: Motion) -> SourceContactResult:
    """Contacts of ``motion`` (on ``body``'s skeleton, e.g. the copy of the source onto its body)."""
    parts = body_parts(body, mapping)
    grot, gpos = motion.global_transforms()
    with torch.no_grad():
        posed = body.pose_vertices(grot, gpos)
    self_contacts = detect_self_contacts(parts, posed, body.height, motion.fps)
    _, rest = body.skeleton.rest_global()
    feet = detect_foot_contacts(gpos, rest, mapping, body.height, motion.fps)
    return SourceContactResult(self_contacts, feet, body.name)


def carry_contacts(
    contacts: SelfContacts, source_body: Character, source_mapping: JointMapping, target: Character,
    target_mapping: JointMapping,
) -> ContactConstraints:
    """The source's hand contacts as target vertex pairs (feature correspondence, paper 1 section 3.4)."""
    if not contacts.count:
        return no_contacts(contacts.num_frames)
    corr = build_correspondence(source_body, source_mapping, target, target_mapping)
    return transfer_contacts(contacts, corr)


def source_contacts_model(found: SourceContactResult, constraints: ContactConstraints) -> SourceContacts:
    """The ``source_contacts`` section of the report."""
    sc = found.self_contacts
    frame, si, sj = sc.vertex_pairs()
    pairs = ContactVertexPairs(
        frame=frame.tolist(), source_i=si.tolist(), source_j=sj.tolist(),
        target_i=constraints.i.tolist(), target_j=constraints.j.tolist(),
    )  # fmt: skip
    return SourceContacts(
        self_contacts=sc.count,
        self_contact_frames=int(sc.frames_with_contact().sum()),
        constraints=constraints.count,
        pairs=[SelfContactEntry.model_validate(e) for e in sc.summary()],
        foot_contact_frames=int(found.feet.labels.any(-1).sum()),
        source_body=found.body_name,
        vertex_pairs=pairs if constraints.count == len(pairs.frame) else None,
    )


@dataclass
class JobMeasurement:
    """Everything measured for one motion x target."""

    report: MetricsReport
    source: SourceContactResult
    constraints: ContactConstraints
    before: ClipMeasures
    after: ClipMeasures | None


def measure_job(
    source_body: Character,
    source_mapping: JointMapping,
    source_view: Motion,
    target: Character,
    target_mapping: JointMapping,
    before: Motion,
    after: Motion | None = None,
    *,
    reference: Motion | None = None,
    source_contacts: SourceContactResult | None = None,
    constraints: ContactConstraints | None = None,
    include_series: bool = True,
    context: dict[str, Any] | None = None,
    notes: list[str] | None = None,
    threads: int | None = MEASURE_THREADS,
    measure_source_motion: bool = True,
    every_frame: bool = False,
) -> JobMeasurement:
    """Detect contacts on the source (unless given), carry them to the target, and measure "before" (and
    "after", against "before") on the target; ``constraints``: the contacts already carried to the target
    (default: carried here); ``reference`` is a ground-truth motion on the target if any.
    All motions must have the same frame count (the pipeline's motions do). ``threads``: torch threads
    while measuring (see :data:`MEASURE_THREADS`; None keeps the current setting). ``measure_source_motion``:
    also measure the source on its own body (the report's ``source``, its warnings in ``notes``).
    ``every_frame``: measure every frame and every hand-to-part distance exactly, "after" without copying the
    frames it shares with "before" (the reference the default path is tested and benchmarked against)."""
    with torch_threads(threads):
        lengths = {"source view": source_view.num_frames, "before": before.num_frames}
        if after is not None:
            lengths["after"] = after.num_frames
        if reference is not None:
            lengths["reference"] = reference.num_frames
        if len(set(lengths.values())) != 1:
            raise ValueError(f"the motions to measure must have the same number of frames, got {lengths}")
        timings: dict[str, float] = {}
        t = time.perf_counter()
        found = source_contacts or detect_source_contacts(source_body, source_mapping, source_view)
        timings["contacts"] = time.perf_counter() - t
        t = time.perf_counter()
        if constraints is None:
            constraints = carry_contacts(found.self_contacts, source_body, source_mapping, target, target_mapping)
        timings["correspondence"] = time.perf_counter() - t
        t = time.perf_counter()
        sdf = body_assets(target, target_mapping)[0].sdf
        timings["sdf"] = time.perf_counter() - t
        t = time.perf_counter()
        ref_measures = None
        if reference is not None:
            _, ref_measures = compute_metrics(target, target_mapping, sdf, reference)
        hands = found.self_contacts.distances  # the source's hand-to-part distances, for the false contacts
        before_metrics, before_measures = compute_metrics(
            target, target_mapping, sdf, before, contacts=constraints, reference=ref_measures, source_feet=found.feet,
            source_hand_distances=hands, cull_hands=not every_frame, deep_causes=after is None or after is before,
        )  # why frames are deeper than 1 cm: read on the result (the copy's, deep nearly everywhere, cost 2.5 s a job)
        after_metrics, after_measures = None, None
        if after is before:  # no stage changed the copy: the same measures, summarised against themselves
            after_metrics = summarize(before_measures, before_measures, ref_measures, found.feet)
            after_measures = before_measures
        elif after is not None:
            after_metrics, after_measures = compute_metrics(
                target, target_mapping, sdf, after, contacts=constraints, original=before_measures,
                reference=ref_measures, source_feet=found.feet, source_hand_distances=hands,
                reuse=None if every_frame else Reuse(before, before_measures), cull_hands=not every_frame,
            )  # fmt: skip
        timings["metrics"] = time.perf_counter() - t
        t = time.perf_counter()
        source = None
        if measure_source_motion:
            source_sdf = body_assets(source_body, source_mapping)[0].sdf
            source = measure_source(source_body, source_mapping, source_view, source_sdf, found.feet)[0]
        timings["source"] = time.perf_counter() - t
        report = build_metrics_report(
            before.name, target.name, target.height, before_metrics, after_metrics, source_contacts_model(found, constraints),
            {k: round(v, 4) for k, v in timings.items()}, notes, context, include_series, source,
            [m.as_dict() for m in target.meshes],
        )  # fmt: skip
        return JobMeasurement(report, found, constraints, before_measures, after_measures)


__all__ = [
    "JobMeasurement",
    "MEASURE_THREADS",
    "SourceContactResult",
    "carry_contacts",
    "detect_source_contacts",
    "measure_job",
    "source_contacts_model",
    "torch_threads",
]
