"""The pairs the acceptance judge tests (ACCEPTANCE.md): which body-part clusters' vertices are tested against
which clusters, as tables over :data:`retarget_core.body_parts.CLUSTERS` and over the part SDFs' segments."""

from __future__ import annotations

import torch
from torch import Tensor

from retarget_core.body_parts import CLUSTERS
from retarget_core.energy.sdf import PartSDF

JUDGED_TESTS: dict[str, tuple[str, ...]] = {
    "left_arm": ("torso", "head", "right_arm", "left_leg", "right_leg"),
    "right_arm": ("torso", "head", "left_arm", "left_leg", "right_leg"),
    "left_leg": ("right_leg", "left_arm", "right_arm"),
    "right_leg": ("left_leg", "left_arm", "right_arm"),
    "head": ("torso",),
}
"""ACCEPTANCE.md's tests, vertex cluster -> clusters it is tested against (the head in the torso is reported apart;
torso vertices are never tested): the only pairs the collision stage measures and resolves."""


def judged_cluster_table(tests: dict[str, tuple[str, ...]] | None = None) -> Tensor:
    """``(C, C)`` bool over :data:`CLUSTERS`: vertex cluster x segment cluster tested (default :data:`JUDGED_TESTS`)."""
    tests = JUDGED_TESTS if tests is None else tests
    out = torch.zeros(len(CLUSTERS), len(CLUSTERS), dtype=torch.bool)
    for a, bs in tests.items():
        for b in bs:
            out[CLUSTERS.index(a), CLUSTERS.index(b)] = True
    return out


def judged_allowed(sdf: PartSDF, tests: dict[str, tuple[str, ...]] | None = None) -> Tensor:
    """``(S, S)`` bool: ``sdf.allowed`` (vertex segment x segment) restricted to the judged cluster pairs."""
    cluster = torch.tensor(sdf.parts.cluster, dtype=torch.long)
    table = judged_cluster_table(tests)
    return sdf.allowed & table[cluster[:, None], cluster[None, :]]


__all__ = ["JUDGED_TESTS", "judged_allowed", "judged_cluster_table"]
