"""Motion: a clip of local joint transforms on a skeleton at an explicit frame rate."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from retarget_core import kinematics
from retarget_core.skeleton import Skeleton


@dataclass
class Motion:
    """A clip in metres, Y up.

    skeleton: the joints the clip animates, with the rest pose the clip was authored against.
    fps: frames per second.
    rotations: ``(F, J, 4)`` local rotations ``xyzw``.
    translations: ``(F, J, 3)`` local translations (the root's is its world position; other joints usually
        repeat their rest offset).
    name: a label, usually the file stem.
    """

    skeleton: Skeleton
    fps: float
    rotations: Tensor
    translations: Tensor
    name: str = "motion"

    def __post_init__(self) -> None:
        f, j = self.rotations.shape[:2]
        if self.rotations.shape != (f, j, 4) or self.translations.shape != (f, j, 3):
            raise ValueError("rotations must be (F, J, 4) and translations (F, J, 3)")
        if j != self.skeleton.num_joints:
            raise ValueError("the motion's joint count differs from its skeleton's")
        if self.fps <= 0:
            raise ValueError("fps must be positive")

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the end of the last one: ``F / fps``."""
        return self.num_frames / self.fps

    def global_transforms(self) -> tuple[Tensor, Tensor]:
        """World rotations ``(F, J, 4)`` and positions ``(F, J, 3)`` of every frame."""
        return kinematics.forward_kinematics(self.skeleton.parents, self.rotations, self.translations)

    def to(self, device: torch.device) -> Motion:
        """The same motion with its tensors on ``device`` (itself when already there)."""
        if self.rotations.device == device and self.translations.device == device:
            return self
        return Motion(self.skeleton, self.fps, self.rotations.to(device), self.translations.to(device), self.name)

    def slice(self, start: int = 0, stop: int | None = None) -> Motion:
        """Frames ``start:stop`` as a new motion."""
        return Motion(
            self.skeleton,
            self.fps,
            self.rotations[start:stop].clone(),
            self.translations[start:stop].clone(),
            self.name,
        )
