"""The decoder run in batched windows (ESO's inner loop): the plain decode exactly, a perturbed one closely."""

from __future__ import annotations

import pytest
import torch

from retarget_core.model.inference import shipped_network
from retarget_core.model.network import RecurrentRetargeter
from retarget_core.model.windowed_decode import WARM_UP_FRAMES, WINDOW_FRAMES, decode_windows, plan_windows

FRAMES = 170


@pytest.fixture(scope="module")
def model() -> RecurrentRetargeter:
    return shipped_network()


def _states(model: RecurrentRetargeter) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    states = 0.3 * torch.randn(1, FRAMES, model.config.hidden, generator=g)
    embedding = torch.randn(1, model.decoder.input_size - model.config.hidden, generator=g)
    return states, embedding


@pytest.mark.parametrize("first", [0, 7, WINDOW_FRAMES + 3, FRAMES - 5])
def test_plain_states_decode_as_the_whole_clip(model: RecurrentRetargeter, first: int) -> None:
    states, embedding = _states(model)
    windows = plan_windows(model, states, embedding, first)
    with torch.no_grad():
        rot6, root = model.decode(states, embedding)
        w_rot6, w_root = decode_windows(model, windows, states, embedding)
    assert w_rot6.shape == (1, FRAMES - first, *rot6.shape[2:])
    torch.testing.assert_close(w_rot6, rot6[:, first:], atol=1e-5, rtol=0)
    torch.testing.assert_close(w_root, root[:, first:], atol=1e-5, rtol=0)


def test_an_offset_reaches_later_windows_through_the_warm_up(model: RecurrentRetargeter) -> None:
    """An offset on frames 30..59 moves the windowed decode about as the whole-clip decode, on its own frames and
    on the next window's (through the warm-up); the difference is the decoder's forgotten memory."""
    states, embedding = _states(model)
    windows = plan_windows(model, states, embedding, 0)
    moved = states.clone()
    moved[:, 30:60] += 0.5 * torch.randn(1, 30, states.shape[-1], generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        rot6, _ = model.decode(moved, embedding)
        plain, _ = model.decode(states, embedding)
        w_rot6, _ = decode_windows(model, windows, moved, embedding)
    change = (rot6 - plain).abs().amax((0, 2, 3))
    error = (w_rot6 - rot6).abs().amax((0, 2, 3))
    assert float(change[30:60].max()) > 0.05  # the offset does move the output
    assert float(error.max()) < 0.005 * float(change.max())  # no warm-up: 0.4, five frames: 0.025


def test_windows_are_batched_with_a_warm_up(model: RecurrentRetargeter) -> None:
    states, embedding = _states(model)
    windows = plan_windows(model, states, embedding, 50)
    steps = WINDOW_FRAMES + WARM_UP_FRAMES
    assert windows.frames.shape == (-(-(FRAMES - 50) // WINDOW_FRAMES), steps)
    assert int(windows.frames[0, 0]) == 50 - WARM_UP_FRAMES
    assert windows.hidden.shape == (model.config.layers, windows.frames.shape[0], model.config.hidden)
