"""Frame-range selection and frame-rate conversion of motions."""

from __future__ import annotations

import torch

from retarget_core import rotations as rot
from retarget_core.errors import RetargetError
from retarget_core.motion import Motion


def select_frames(motion: Motion, start: int = 0, end: int | None = None) -> Motion:
    """Frames ``start:end`` (end exclusive); a range outside the clip raises a clear error."""
    n = motion.num_frames
    stop = n if end is None else end
    if start >= n or stop <= start:
        raise RetargetError(f"frame range {start}:{end} is outside the clip's {n} frames")
    return motion.slice(start, min(stop, n))


def resample(motion: Motion, fps: float) -> Motion:
    """The motion at ``fps``: rotations slerped, translations interpolated linearly.

    The duration is kept: ``F_out = round((F_in - 1) * fps / fps_in) + 1`` frames spanning the same time."""
    if abs(fps - motion.fps) < 1e-6:
        return motion
    n_in = motion.num_frames
    n_out = max(1, round((n_in - 1) * fps / motion.fps) + 1)
    t = torch.arange(n_out, dtype=torch.float32) * (motion.fps / fps)
    t = t.clamp(max=n_in - 1)
    i0 = t.floor().long().clamp(max=n_in - 1)
    i1 = (i0 + 1).clamp(max=n_in - 1)
    w = t - i0.float()
    q0, q1 = motion.rotations[i0], motion.rotations[i1]
    # Shortest path: flip q1 where it lies in the other hemisphere.
    wq = w[:, None].expand(n_out, q0.shape[1])
    rotations = rot.normalize(rot.slerp(q0, q1, wq))
    wt = w[:, None, None]
    translations = motion.translations[i0] * (1 - wt) + motion.translations[i1] * wt
    return Motion(motion.skeleton, fps, rotations, translations, motion.name)
