"""The geometry-conditioned recurrent retargeter (paper 1, section 3.2 and appendix B), small.

    source features (B, F, SOURCE_DIM) -> normalise -> Linear -> encoder GRU (L x H) -> h_enc (B, F, H)
    target code (B, TARGET_DIM)        -> normalise -> MLP -> e (B, E)
      (geometry "pointnet": the code without its girths, and a PointNet code of the geometry points
       (B, POINTS, POINT_DIM) -> shared MLP -> max pool -> Linear -> (B, point_code), into the MLP)
    [h_enc, e] -> decoder GRU (L x H) -> linear heads: residual rotations (B, F, 22, 6), root offset (B, F, 3)

Differences from the paper: 2 x 128 units instead of 2 x 512 (about 16x fewer recurrent weights: 0.5 M
parameters, 2 MB; its speed in docs/model-recurrent.md), and the decoder is not autoregressive
(it does not read its own previous output: the whole clip runs as one GRU call, and ESO can optimise the
encoder states of every frame at once). The heads are zero-initialised, so an untrained network outputs the
copy baseline exactly (see :func:`retarget_core.model.features.apply_residual`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from retarget_core.model.features import GIRTHS, NUM_CANONICAL, POINT_DIM, SOURCE_DIM, TARGET_DIM

GEOMETRIES = ("girths", "pointnet")


@dataclass(frozen=True)
class NetworkConfig:
    """Sizes. hidden: GRU units per layer; layers: GRU layers (encoder and decoder each); code: width of the
    target code embedding; dropout: between GRU layers and on the embedding (paper: 0.1); geometry: how the
    body's shape enters the target code, "girths" (per-segment girths, the shipped weights) or "pointnet" (a
    PointNet over sampled rest vertices and skin weights instead); point_hidden, point_code: the PointNet's
    shared-MLP width and output width."""

    hidden: int = 128
    layers: int = 2
    code: int = 64
    dropout: float = 0.1
    geometry: str = "girths"
    point_hidden: int = 64
    point_code: int = 32

    def __post_init__(self) -> None:
        if self.geometry not in GEOMETRIES:
            raise ValueError(f"unknown geometry {self.geometry!r}; one of {', '.join(GEOMETRIES)}")


class PointNet(nn.Module):
    """Shared MLP over points ``(B, N, POINT_DIM)``, max pool, linear: a code ``(B, out)`` blind to the point
    order and count, so any mesh topology works."""

    def __init__(self, hidden: int, out: int) -> None:
        super().__init__()
        self.shared = nn.Sequential(nn.Linear(POINT_DIM, hidden), nn.ReLU(), nn.Linear(hidden, 2 * hidden), nn.ReLU())
        self.out = nn.Linear(2 * hidden, out)

    def forward(self, points: Tensor) -> Tensor:
        return self.out(self.shared(points).amax(dim=-2))


def _code_columns(geometry: str) -> Tensor:
    """The target code's columns the embedding reads: all of them, or all but the girths for "pointnet"."""
    keep = torch.ones(TARGET_DIM, dtype=torch.bool)
    if geometry == "pointnet":
        keep[GIRTHS] = False
    return keep.nonzero()[:, 0]


class RecurrentRetargeter(nn.Module):
    """Encoder-decoder GRU with residual heads (see module doc)."""

    source_mean: Tensor
    source_std: Tensor
    target_mean: Tensor
    target_std: Tensor
    code_columns: Tensor

    def __init__(self, config: NetworkConfig | None = None) -> None:
        super().__init__()
        self.config = config or NetworkConfig()
        c = self.config
        self.register_buffer("source_mean", torch.zeros(SOURCE_DIM))
        self.register_buffer("source_std", torch.ones(SOURCE_DIM))
        self.register_buffer("target_mean", torch.zeros(TARGET_DIM))
        self.register_buffer("target_std", torch.ones(TARGET_DIM))
        self.register_buffer("code_columns", _code_columns(c.geometry), persistent=False)
        self.pointnet = PointNet(c.point_hidden, c.point_code) if c.geometry == "pointnet" else None
        code_in = len(self.code_columns) + (c.point_code if self.pointnet is not None else 0)
        self.source_in = nn.Linear(SOURCE_DIM, c.hidden)
        self.encoder = nn.GRU(c.hidden, c.hidden, c.layers, batch_first=True, dropout=c.dropout)
        self.target_in = nn.Sequential(
            nn.Linear(code_in, c.code), nn.ReLU(), nn.Dropout(c.dropout), nn.Linear(c.code, c.code), nn.ReLU()
        )
        self.decoder = nn.GRU(c.hidden + c.code, c.hidden, c.layers, batch_first=True, dropout=c.dropout)
        self.rotation_head = nn.Linear(c.hidden, NUM_CANONICAL * 6)
        self.root_head = nn.Linear(c.hidden, 3)
        for head in (self.rotation_head, self.root_head):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def set_normalisation(self, source: Tensor, target: Tensor) -> None:
        """Feature statistics from training samples ``(N, SOURCE_DIM)`` and ``(M, TARGET_DIM)``."""
        self.source_mean.copy_(source.mean(0))
        self.source_std.copy_(source.std(0).clamp_min(1e-3))
        # Few training bodies: one scale for the whole target code (a per-dimension deviation over a handful of
        # bodies would magnify differences no held-out body respects).
        self.target_mean.copy_(target.mean(0))
        spread = (target - target.mean(0)).pow(2).mean().sqrt() if target.shape[0] > 1 else target.new_tensor(1.0)
        self.target_std.fill_(float(spread.clamp_min(1e-3)))

    def encode(self, source: Tensor) -> Tensor:
        """Encoder states ``(B, F, H)`` of source features ``(B, F, SOURCE_DIM)``."""
        x = self.source_in((source - self.source_mean) / self.source_std)
        h, _ = self.encoder(torch.relu(x))
        return h

    def embed(self, target: Tensor, points: Tensor | None = None) -> Tensor:
        """Target embedding ``(B, E)`` of target codes ``(B, TARGET_DIM)`` and, for the "pointnet" geometry,
        the geometry points ``(B or 1, POINTS, POINT_DIM)`` (one body's points serve the whole batch)."""
        x = ((target - self.target_mean) / self.target_std)[:, self.code_columns]
        if self.pointnet is not None:
            if points is None:
                raise ValueError("a pointnet network needs the geometry points (TargetRig.points)")
            x = torch.cat([x, self.pointnet(points).expand(x.shape[0], -1)], dim=-1)
        return self.target_in(x)

    def decoder_input(self, states: Tensor, embedding: Tensor) -> Tensor:
        """The decoder's input ``(B, F, H + E)``: encoder states ``(B, F, H)`` beside the embedding ``(B, E)``."""
        return torch.cat([states, embedding[:, None, :].expand(-1, states.shape[1], -1)], dim=-1)

    def heads(self, h: Tensor) -> tuple[Tensor, Tensor]:
        """Residual rotations ``(B, F, 22, 6)`` and root offsets ``(B, F, 3)`` of decoder outputs ``(B, F, H)``."""
        return self.rotation_head(h).view(*h.shape[:2], NUM_CANONICAL, 6), self.root_head(h)

    def decode(self, states: Tensor, embedding: Tensor) -> tuple[Tensor, Tensor]:
        """Residual rotations ``(B, F, 22, 6)`` and root offsets ``(B, F, 3)`` from encoder states and the
        target embedding."""
        h, _ = self.decoder(self.decoder_input(states, embedding))
        return self.heads(h)

    def forward(self, source: Tensor, target: Tensor, points: Tensor | None = None) -> tuple[Tensor, Tensor]:
        return self.decode(self.encode(source), self.embed(target, points))


def save_network(model: RecurrentRetargeter, path: str | Path, meta: dict[str, Any]) -> None:
    """Weights, configuration and ``meta`` (training settings, figures) in one file (float32)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().float().cpu() for k, v in model.state_dict().items()}
    torch.save({"config": asdict(model.config), "state": state, "meta": meta}, path)


def load_network(path: str | Path, device: torch.device | str = "cpu") -> tuple[RecurrentRetargeter, dict[str, Any]]:
    """The network saved by :func:`save_network`, in eval mode on ``device``, and its meta."""
    blob = torch.load(Path(path), map_location="cpu", weights_only=True)
    model = RecurrentRetargeter(NetworkConfig(**blob["config"]))
    model.load_state_dict(blob["state"])
    model.eval()
    return model.to(device), dict(blob.get("meta", {}))


__all__ = ["GEOMETRIES", "NetworkConfig", "PointNet", "RecurrentRetargeter", "load_network", "save_network"]
