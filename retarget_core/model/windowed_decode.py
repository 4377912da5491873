"""The decoder run over a stretch of frames as many short windows at once instead of one long sequence.

ESO differentiates the decoder's recurrence on every step; a 300-frame clip makes 300 sequential GRU steps and
as many in the backward pass, each a handful of tiny operations. Here frames ``first .. last - 1`` are cut into
windows of ``length`` frames, each decoded after ``warm_up`` frames that it decodes and drops, starting from the
hidden state the plain decode (the states without ESO's offsets) had there; all windows run as one batch.

The decoder forgets: on the shipped network ESO's offsets move the decoder's output by up to 0.24 (rot6 units)
where they act, by at most 4e-4 twenty frames later and 7e-5 thirty frames later; with a 30-frame warm-up the
windowed decode differs from the whole-clip decode by at most 8e-4 (`benchmarks/diag/decoder_memory.py`,
docs/results.md "ESO in windows"). The network was trained on 60-frame windows.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from retarget_core.model.network import RecurrentRetargeter

WINDOW_FRAMES = 40  # frames kept per window
WARM_UP_FRAMES = 30  # frames decoded and dropped before them (the decoder's memory, see the module doc)


@dataclass(frozen=True)
class DecodeWindows:
    """How frames ``first .. last - 1`` are decoded. frames ``(B, T)``: the frame read at each step of each window
    (T = warm-up + length; clamped to the last frame past the end); keep ``(last - first,)``: each frame's output
    in the flattened ``(B * T)`` outputs; hidden ``(layers, B, H)``: the plain decode's state before each window."""

    first: int
    last: int
    frames: Tensor
    keep: Tensor
    hidden: Tensor


def _layers(gru: nn.GRU) -> list[nn.GRU]:
    """One single-layer GRU per layer of ``gru``, sharing its weights (to read every layer's states)."""
    out = []
    for k in range(gru.num_layers):
        size_in = gru.input_size if k == 0 else gru.hidden_size
        one = nn.GRU(size_in, gru.hidden_size, 1, batch_first=gru.batch_first, bias=gru.bias)
        for name in one._flat_weights_names:
            setattr(one, name, getattr(gru, name.replace("_l0", f"_l{k}")))
        out.append(one.eval())
    return out


def plan_windows(model: RecurrentRetargeter, states: Tensor, embedding: Tensor, first: int,
                 length: int = WINDOW_FRAMES, warm_up: int = WARM_UP_FRAMES) -> DecodeWindows:  # fmt: skip
    """Windows over frames ``first .. F - 1`` of the plain ``states (1, F, H)``; ``embedding (1, E)``."""
    last = states.shape[1]
    starts = torch.arange(first, last, length)
    begin = (starts - warm_up).clamp_min(0)  # a window near the clip's start warms up on fewer frames
    steps = warm_up + length
    frames = (begin[:, None] + torch.arange(steps)).clamp(max=last - 1)
    offset = torch.arange(last - first)
    window = offset // length
    keep = window * steps + (starts[window] - begin[window]) + offset % length
    with torch.no_grad():
        x, per_layer = model.decoder_input(states, embedding), []
        for layer in _layers(model.decoder):
            x, _ = layer(x)
            per_layer.append(x[0])  # (F, H)
    before = (begin - 1).clamp_min(0)
    hidden = torch.stack([torch.where((begin > 0)[:, None], h[before], 0.0) for h in per_layer])
    return DecodeWindows(first, last, frames, keep, hidden)


def decode_windows(model: RecurrentRetargeter, windows: DecodeWindows, states: Tensor, embedding: Tensor
                   ) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Residual rotations ``(1, N, 22, 6)`` and root offsets ``(1, N, 3)`` of frames ``first .. last - 1``
    (N of them) from states ``(1, last, H)`` (differentiable), as :meth:`RecurrentRetargeter.decode`."""
    x = model.decoder_input(states, embedding)[0, windows.frames]  # (B, T, H + E)
    h, _ = model.decoder(x, windows.hidden.to(x.dtype))
    return model.heads(h.reshape(-1, h.shape[-1]).index_select(0, windows.keep)[None])


__all__ = ["WARM_UP_FRAMES", "WINDOW_FRAMES", "DecodeWindows", "decode_windows", "plan_windows"]
