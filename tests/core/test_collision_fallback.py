"""The collision stage's never-worse machinery on small tensors: the repair step finds the vertices that went
deeper than on the input."""

from __future__ import annotations

import torch

from retarget_core.metrics.depth import VertexDepths
from retarget_core.refine.collision_check import FrameCheck
from retarget_core.refine.collision_mesh import MeshPairs
from retarget_core.refine.collisions import deepened_points, head_count, head_depth, mesh_inside


def _check(frames: list[int], depth: torch.Tensor) -> FrameCheck:
    return FrameCheck(torch.tensor(frames), depth.sum(1), depth.amax(1), (depth > 0).sum(1).float(),
                      VertexDepths.from_dense(depth), torch.zeros(0))  # fmt: skip


def test_deepened_points_are_the_new_deeper_vertices_of_the_worse_frames() -> None:
    before = _check([0, 1, 2], torch.tensor([[0.0, 0.02, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
    # frame 1 (worse): vertex 0 went in 1 cm, vertex 2 by less than the tolerance; frame 2 (not worse): vertex 3
    after = _check([1, 2], torch.tensor([[0.01, 0.0, 0.001, 0.0], [0.0, 0.0, 0.0, 0.03]]))
    worse = torch.tensor([True, False])
    got = deepened_points(before, after, worse, points=torch.tensor([1]), tol=0.003)
    assert got.tolist() == [0]
    assert deepened_points(before, after, worse, points=torch.tensor([0]), tol=0.003).tolist() == []
    # a vertex as deep as on the input is not new: before frame 1 has vertex 0 at 0.009 m
    before = _check([0, 1, 2], torch.tensor([[0.0, 0.02, 0.0, 0.0], [0.009, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
    assert deepened_points(before, after, worse, points=torch.tensor([1]), tol=0.003).tolist() == []


def test_sparse_depths_read_as_the_dense_array() -> None:
    dense = torch.tensor([[0.0, 0.02, 0.0], [0.0, 0.0, 0.0], [0.01, 0.0, 0.03]])
    d = VertexDepths.from_dense(dense)
    assert d.frame.tolist() == [0, 2, 2] and d.vertex.tolist() == [1, 0, 2]
    frame, vertex = torch.tensor([0, 0, 1, 2, 2, 2]), torch.tensor([0, 1, 1, 0, 1, 2])
    assert torch.equal(d.value_at(frame, vertex), dense[frame, vertex])
    keep = torch.tensor([False, True, True])
    assert torch.equal(d.select_rows(keep).dense(), dense[keep])
    assert d.vertices_of(torch.tensor([2])).tolist() == [0, 2] and d.vertices_of(torch.tensor([1])).tolist() == []
    assert VertexDepths.empty(2, 3).value_at(torch.tensor([1]), torch.tensor([2])).tolist() == [0.0]


def test_mesh_inside_keeps_the_deep_pairs_of_the_given_frames() -> None:
    mesh = MeshPairs(torch.tensor([3, 3, 5, 7]), torch.tensor([10, 11, 12, 13]), torch.zeros(4, 3, dtype=torch.long),
                     torch.ones(4), torch.tensor([0.01, -0.002, 0.02, 0.02]))  # fmt: skip
    kept = mesh_inside(mesh, torch.tensor([3, 5]), tol=0.003)
    assert kept is not None and kept.vertex.tolist() == [10, 12]
    assert mesh_inside(None, torch.tensor([3]), 0.003) is None
    head = torch.zeros(14, dtype=torch.bool)
    head[11] = True  # a head vertex counts at any depth (the judge's head %v): 0.5 mm inside is kept too
    mesh.depth[1] = 0.0005
    kept = mesh_inside(mesh, torch.tensor([3, 5]), tol=0.003, any_depth=head)
    assert kept is not None and kept.vertex.tolist() == [10, 11, 12]


def test_head_depth_reads_the_deepest_head_vertex_per_frame() -> None:
    mesh = MeshPairs(torch.tensor([0, 0, 2, 2]), torch.tensor([1, 2, 1, 3]), torch.zeros(4, 3, dtype=torch.long),
                     torch.ones(4), torch.tensor([0.004, 0.01, -0.002, 0.001]))  # fmt: skip
    head = torch.tensor([False, True, False, True])
    assert torch.allclose(head_depth(mesh, head, 3), torch.tensor([0.004, 0.0, 0.001]))


def test_head_count_reads_the_head_vertices_inside_at_any_depth_per_frame() -> None:
    mesh = MeshPairs(torch.tensor([0, 0, 0, 2, 2]), torch.tensor([1, 2, 3, 1, 3]), torch.zeros(5, 3, dtype=torch.long),
                     torch.ones(5), torch.tensor([0.004, 0.01, 1e-6, -0.002, 0.001]))  # fmt: skip
    head = torch.tensor([False, True, False, True])
    # frame 0: vertex 1 (4 mm) and vertex 3 (a micrometre: the judge counts it); frame 2: vertex 3 only
    assert head_count(mesh, head, 3).tolist() == [2, 0, 1]
