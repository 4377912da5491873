"""The refit triangle tree against libigl on a deformed closed mesh over several frames (small: fast)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor

from retarget_core.geometry.closest_point import closest_points
from retarget_core.geometry.triangle_bvh import (
    PosedBoxes,
    TriangleBVH,
    build_bvh,
    closest_triangles,
    refit,
    winding_numbers,
)


def _frames() -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """A sphere (rest pose) and 5 bulged, moved frames of it."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    rest, faces = np.asarray(m.vertices), np.asarray(m.faces)
    frames = [rest * (1 + 0.3 * np.sin(3 * rest[:, [1, 2, 0]] + k)) + 0.05 * k for k in range(5)]
    return rest, faces, frames


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_closest_triangles_and_winding_numbers_match_libigl_on_every_frame(leaf_size: int) -> None:
    import igl

    rest, faces, frames = _frames()
    tree = build_bvh(rest, faces, leaf_size)
    boxes = refit(tree, torch.from_numpy(np.stack(frames)))
    rng = np.random.default_rng(0)
    q = rng.uniform(-1.5, 1.8, (2000, 3))
    fr = rng.integers(0, len(frames), len(q))
    reach = 0.2
    d, face = closest_triangles(tree, boxes, torch.from_numpy(fr), torch.from_numpy(q), reach)
    w = winding_numbers(tree, boxes, torch.from_numpy(fr), torch.from_numpy(q))
    close_seen = inside_seen = 0
    for k, verts in enumerate(frames):
        sel = fr == k
        d2, _, _ = igl.point_mesh_squared_distance(q[sel], verts, faces)
        ref = np.sqrt(d2)
        mine, mine_face = d.numpy()[sel], face.numpy()[sel]
        close = ref < reach
        assert np.allclose(mine[close], ref[close], atol=1e-12)
        assert np.all(np.isinf(mine[~close])) and np.all(mine_face[~close] == -1)
        v, f = torch.from_numpy(verts), torch.from_numpy(faces)
        x = torch.from_numpy(q[sel][close])
        at_face = (x - closest_points(x, *(v[f[mine_face[close], c]] for c in range(3)))).norm(dim=-1)
        assert np.allclose(at_face.numpy(), ref[close], atol=1e-12)  # a closest triangle (ties: the lowest index)
        inside_ref = np.abs(igl.fast_winding_number(verts, faces, q[sel])) > 0.5
        assert np.array_equal(np.abs(w.numpy()[sel]) > 0.5, inside_ref)
        close_seen, inside_seen = close_seen + int(close.sum()), inside_seen + int(inside_ref.sum())
    assert close_seen > 100 and inside_seen > 100  # both kinds of query were asked


def test_a_point_on_a_shared_edge_gets_the_lower_triangle_and_far_points_none() -> None:
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    tree = build_bvh(verts, faces, leaf_size=1)
    boxes = refit(tree, torch.from_numpy(verts)[None])
    q = torch.tensor([[0.5, 0.5, 0.1], [5.0, 5.0, 5.0]], dtype=torch.float64)  # above the diagonal; far away
    d, face = closest_triangles(tree, boxes, torch.zeros(2, dtype=torch.long), q, 1.0)
    assert math.isclose(float(d[0]), 0.1, abs_tol=1e-12) and int(face[0]) == 0
    assert math.isinf(float(d[1])) and int(face[1]) == -1


def test_an_empty_triangle_set_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="empty"):
        build_bvh(np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64))


def _posed_queries(seed: int, n: int) -> tuple[TriangleBVH, PosedBoxes, Tensor, Tensor, np.random.Generator]:
    """The sphere's tree refit on its 5 frames, ``n`` random query points and their frames, and the generator
    (seeded ``seed``) for what a test draws next."""
    rest, faces, frames = _frames()
    tree = build_bvh(rest, faces)
    boxes = refit(tree, torch.from_numpy(np.stack(frames)))
    rng = np.random.default_rng(seed)
    q = torch.from_numpy(rng.uniform(-1.5, 1.8, (n, 3)))
    fr = torch.from_numpy(rng.integers(0, len(frames), len(q)))
    return tree, boxes, fr, q, rng


def test_queries_walked_in_blocks_read_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    import retarget_core.geometry.triangle_bvh as tb

    tree, boxes, fr, q, _ = _posed_queries(1, 500)
    whole = closest_triangles(tree, boxes, fr, q, 0.2), winding_numbers(tree, boxes, fr, q)
    monkeypatch.setattr(tb, "QUERY_BLOCK", 64)
    blocked = closest_triangles(tree, boxes, fr, q, 0.2), winding_numbers(tree, boxes, fr, q)
    assert torch.equal(whole[0][0], blocked[0][0]) and torch.equal(whole[0][1], blocked[0][1])
    assert torch.equal(whole[1], blocked[1])


def test_a_bound_per_query_reads_as_the_common_bound_cut_at_each_querys_own() -> None:
    tree, boxes, fr, q, rng = _posed_queries(2, 2000)
    bound = torch.from_numpy(rng.choice([0.02, 0.2], len(q)))
    d_all, face_all = closest_triangles(tree, boxes, fr, q, 0.2)
    d, face = closest_triangles(tree, boxes, fr, q, bound)
    within = d_all <= bound
    assert int(within.sum()) > 50 and int((~within & (face_all >= 0)).sum()) > 50  # both kinds were asked
    assert torch.equal(d[within], d_all[within]) and torch.equal(face[within], face_all[within])
    assert bool(torch.isinf(d[~within]).all()) and bool((face[~within] == -1).all())


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_the_compiled_walks_read_as_the_tensor_walks(leaf_size: int) -> None:
    """The CPU's compiled walks against the tensor walks (the reference) on the same posed trees, with frames
    stored once for several (``rows``), per-query bounds, and points on, near and inside the surface."""
    from retarget_core.geometry.triangle_bvh import tensor_closest_triangles, tensor_winding_numbers

    rest, faces, frames = _frames()
    tree = build_bvh(rest, faces, leaf_size)
    stored = refit(tree, torch.from_numpy(np.stack(frames)))
    rng = np.random.default_rng(3)
    boxes = PosedBoxes(stored.lo, stored.hi, stored.vertices, torch.from_numpy(rng.integers(0, 5, 7)))
    fr = torch.from_numpy(rng.integers(0, 7, 6000))
    on_surface = torch.from_numpy(np.stack(frames))[boxes.rows[fr[:300]], torch.from_numpy(faces[:300, 0])]
    q = torch.cat([on_surface, torch.from_numpy(rng.uniform(-1.5, 1.8, (len(fr) - 300, 3)))])
    bound = torch.from_numpy(rng.choice([0.0, 0.02, 0.3, 5.0], len(q)))
    d, face = closest_triangles(tree, boxes, fr, q, bound)
    d_ref, face_ref = tensor_closest_triangles(tree, boxes, fr, q, bound)
    assert torch.allclose(d, d_ref, atol=1e-12, rtol=0) and torch.equal(torch.isinf(d), torch.isinf(d_ref))
    assert float((face == face_ref).double().mean()) > 0.999  # ties at shared edges within 1e-12 may differ
    assert int((face >= 0).sum()) > 1500 and int((d == 0).sum()) >= 300  # near, far and on-surface were asked
    off = slice(300, None)  # on the surface a ray's crossings are a matter of rounding (either walk: not 0 or 1)
    w, w_ref = winding_numbers(tree, boxes, fr[off], q[off]), tensor_winding_numbers(tree, boxes, fr[off], q[off])
    assert torch.equal(w, w_ref) and int((w.abs() > 0.5).sum()) > 500


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_the_compiled_refit_gives_the_tensor_refits_boxes(leaf_size: int) -> None:
    import retarget_core.geometry.triangle_bvh as tb

    rest, faces, frames = _frames()
    tree = build_bvh(rest, faces, leaf_size)
    posed = torch.from_numpy(np.stack(frames * 4))  # 20 frames: blocks on threads
    compiled = refit(tree, posed)
    lo, hi = tb._leaf_boxes(tree, posed, torch.arange(len(tree.leaf_faces)))
    leaves = compiled.level(tree.depth)
    assert torch.equal(compiled.lo[:, leaves], lo) and torch.equal(compiled.hi[:, leaves], hi)
    for level in range(tree.depth):
        lo, hi = tb._parent_boxes(lo, hi)
        here = compiled.level(tree.depth - 1 - level)
        assert torch.equal(compiled.lo[:, here], lo) and torch.equal(compiled.hi[:, here], hi)


def test_indexed_bounds_equal_the_gathered_min_and_max() -> None:
    """The compiled box of some rows of each frame equals min and max over the gathered rows."""
    from retarget_core.geometry.bvh_kernels import indexed_bounds

    posed = torch.randn(7, 200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    index = np.array([5, 0, 199, 42, 42, 17])
    lo, hi = np.empty((7, 3)), np.empty((7, 3))
    indexed_bounds(posed.numpy(), index, lo, hi)
    assert np.array_equal(lo, posed[:, index].amin(dim=1).numpy())
    assert np.array_equal(hi, posed[:, index].amax(dim=1).numpy())


@pytest.mark.parametrize("frames", [3, 40])
def test_rows_in_boxes_equal_the_gathered_test_in_the_same_order(frames: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled rows of each frame inside its box are those of ``nonzero`` on the gathered comparison, in its
    order (frame, then place in the index), a row on a box face counting as inside; in one block and in blocks on
    threads."""
    from retarget_core.geometry import bvh_kernels
    from retarget_core.geometry.bvh_kernels import rows_bounds, rows_in_boxes

    monkeypatch.setattr(bvh_kernels, "MIN_ROWS", 8)  # 40 frames of 7 rows: blocks of a frame and more

    gen = torch.Generator().manual_seed(5)
    posed = torch.randn(frames, 300, 3, dtype=torch.float64, generator=gen)
    index = torch.tensor([7, 0, 299, 42, 42, 150, 3])
    lo = torch.randn(frames, 3, dtype=torch.float64, generator=gen) - 0.5
    hi = lo + 1.5
    lo[0] = posed[0, 42]  # on its box's low corner: inside
    lo[1], hi[1] = math.inf, -math.inf  # an empty box: nothing inside
    f, k = rows_in_boxes(posed.numpy(), index.numpy(), lo.numpy(), hi.numpy())
    at = posed[:, index]
    want_f, want_k = torch.nonzero(((at >= lo[:, None]) & (at <= hi[:, None])).all(dim=-1), as_tuple=True)
    assert len(want_f) > 0 and 1 not in f.tolist()
    assert np.array_equal(f, want_f.numpy()) and np.array_equal(k, want_k.numpy())
    b_lo, b_hi = rows_bounds(posed.numpy(), index.numpy())
    assert np.array_equal(b_lo, at.amin(dim=1).numpy()) and np.array_equal(b_hi, at.amax(dim=1).numpy())


def _blocks_sum(count: int) -> int:
    """Sum of 0..count-1 through :func:`run_in_blocks` on two threads."""
    from retarget_core.geometry.bvh_kernels import run_in_blocks

    out = np.zeros(count, dtype=np.int64)
    torch.set_num_threads(2)

    def walk(b: slice) -> None:
        out[b] = np.arange(count)[b]

    run_in_blocks(walk, count, 1)
    return int(out.sum())


def test_blocks_run_in_a_forked_worker_after_the_parent_used_its_threads() -> None:
    """The thread pool is kept for the process: a child forked after the parent ran blocks on it (a Celery
    worker) still runs its blocks."""
    import multiprocessing

    assert _blocks_sum(100) == 4950
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert pool.apply_async(_blocks_sum, (100,)).get(timeout=60) == 4950
