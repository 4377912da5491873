"""The collision stage's never-worse machinery on small tensors: the repair step finds the vertices that went
deeper than on the input."""

from __future__ import annotations

import torch

from retarget_core.refine.collision_check import FrameCheck
from retarget_core.refine.collision_mesh import MeshPairs
from retarget_core.refine.collisions import deepened_points, mesh_inside


def _check(frames: list[int], depth: torch.Tensor) -> FrameCheck:
    return FrameCheck(torch.tensor(frames), depth.sum(1), depth.amax(1), (depth > 0).sum(1).float(), depth, torch.zeros(0))


def test_deepened_points_are_the_new_deeper_vertices_of_the_worse_frames() -> None:
    before = _check([0, 1, 2], torch.tensor([[0.0, 0.02, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
    # frame 1 (worse): vertex 0 went in 1 cm, vertex 2 by less than the tolerance; frame 2 (not worse): vertex 3
    after = _check([1, 2], torch.tensor([[0.01, 0.0, 0.001, 0.0], [0.0, 0.0, 0.0, 0.03]]))
    worse = torch.tensor([True, False])
    got = deepened_points(before, after, worse, points=torch.tensor([1]), tol=0.003)
    assert got.tolist() == [0]
    assert deepened_points(before, after, worse, points=torch.tensor([0]), tol=0.003).tolist() == []


def test_mesh_inside_keeps_the_deep_pairs_of_the_given_frames() -> None:
    mesh = MeshPairs(torch.tensor([3, 3, 5, 7]), torch.tensor([10, 11, 12, 13]), torch.zeros(4, 3, dtype=torch.long),
                     torch.ones(4), torch.tensor([0.01, -0.002, 0.02, 0.02]))  # fmt: skip
    kept = mesh_inside(mesh, torch.tensor([3, 5]), tol=0.003)
    assert kept is not None and kept.vertex.tolist() == [10, 12]
    assert mesh_inside(None, torch.tensor([3]), 0.003) is None
