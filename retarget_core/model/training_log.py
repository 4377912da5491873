"""The training loops' bookkeeping: one JSON line of losses per step, their moving averages, the time budget."""

from __future__ import annotations

import json
import time
from pathlib import Path
from types import TracebackType
from typing import IO, Any

EMA_DECAY, EMA_SHARE = 0.98, 0.02  # the moving averages follow about the last 50 steps


class TrainingLog:
    """Per step: ``record`` the loss and its terms (written to ``path`` as one JSON line when given, averaged in
    :attr:`ema`); :meth:`out_of_time` once ``max_minutes`` of training have passed. A context manager."""

    def __init__(self, path: Path | None, max_minutes: float) -> None:
        self.file: IO[str] | None = path.open("w") if path is not None else None
        self.t0 = time.perf_counter()
        self.max_seconds = max_minutes * 60.0
        self.last: dict[str, Any] = {}
        self.ema: dict[str, float] = {}

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.t0

    def record(self, step: int, body: int, loss: float, terms: dict[str, float], lr: float) -> dict[str, Any]:
        """The step's row (step, body, loss, terms, lr, seconds), written and averaged."""
        self.last = {"step": step, "body": body, "loss": loss, **terms, "lr": lr, "seconds": round(self.seconds, 2)}
        for k in ("loss", *terms):
            v = self.last[k]
            self.ema[k] = v if k not in self.ema else EMA_DECAY * self.ema[k] + EMA_SHARE * v
        if self.file is not None:
            self.file.write(json.dumps(self.last) + "\n")
            self.file.flush()
        return self.last

    def out_of_time(self) -> bool:
        return self.seconds > self.max_seconds

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None

    def __enter__(self) -> TrainingLog:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


__all__ = ["EMA_DECAY", "TrainingLog"]
