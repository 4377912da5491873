"""The compiled row posing (:mod:`retarget_core.geometry.skin_rows`): the gather-and-blend form's values and
gradient, padded influences skipped."""

from __future__ import annotations

import torch

from retarget_core.geometry.skin_rows import skin_rows


def _rows(n: int, t: int, k: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` rows of ``k`` influences among ``t`` transforms, some weights zero (padding), float64."""
    g = torch.Generator().manual_seed(seed)
    mat_rows = torch.randint(0, t, (n, k), generator=g)
    weight = torch.rand(n, k, generator=g, dtype=torch.float64)
    weight[:, 1:] *= torch.rand(n, k - 1, generator=g, dtype=torch.float64) < 0.5
    return mat_rows, weight / weight.sum(1, keepdim=True), torch.randn(n, 3, generator=g, dtype=torch.float64)


def _blend(mat_rows: torch.Tensor, weight: torch.Tensor, rest: torch.Tensor, mats: torch.Tensor) -> torch.Tensor:
    """The reference: every influence's transform applied to the rest position, weighted."""
    m = mats[mat_rows]  # (N, K, 3, 4)
    applied = (m[..., :3] @ rest[:, None, :, None])[..., 0] + m[..., 3]  # (N, K, 3)
    return (weight[..., None] * applied).sum(1)


def test_rows_and_their_gradient_equal_the_blended_form() -> None:
    mat_rows, weight, rest = _rows(200, 12, 4, 0)
    mats = torch.randn(12, 3, 4, dtype=torch.float64, requires_grad=True)
    grad = torch.randn(200, 3, dtype=torch.float64)
    got = skin_rows(mat_rows, weight, rest, mats)
    (g_got,) = torch.autograd.grad((got * grad).sum(), mats)
    want = _blend(mat_rows, weight, rest, mats)
    (g_want,) = torch.autograd.grad((want * grad).sum(), mats)
    assert torch.allclose(got, want, atol=1e-12)
    assert torch.allclose(g_got, g_want, atol=1e-12)
    assert g_want.abs().max() > 1.0  # the gradient is not trivially zero


def test_float32_rows_and_a_padded_influence_that_points_anywhere() -> None:
    """A zero weight's transform index is never read: its transform may hold anything, even NaN."""
    mat_rows, weight, rest = _rows(50, 6, 3, 1)
    weight[:, 2] = 0.0
    mat_rows[:, :2] %= 5
    mat_rows[:, 2] = 5
    mats = torch.randn(6, 3, 4)
    mats[5] = float("nan")
    got = skin_rows(mat_rows, weight, rest, mats)
    assert got.dtype == torch.float32 and torch.isfinite(got).all()
    assert torch.allclose(got, _blend(mat_rows[:, :2], weight[:, :2].float(), rest.float(), mats), atol=1e-5)
