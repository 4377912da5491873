"""Foot contact with the ground (paper 1, section 3.4), on a source motion or on any result.

The toe (``ToeBase``) is in contact when its height above its standing height is at most 3 cm and it moved at
most 1 cm since the previous frame; the heel (the ``Foot`` joint, the ankle on Mixamo-style rigs) when it moved
at most 1 cm. Thresholds are at a 1.80 m character and 30 fps and are scaled to the body and the clip's frame
rate (the paper's clips are 30 fps; a 60 fps clip moves half as far per frame). Heights are measured above the
joint's height in the rest pose standing on the ground (the paper adds the reference-pose heel height so high
heels do not break the test). A window of 5 frames then fills in contacts: a frame becomes a contact when more
than half of the window around it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from retarget_core.canonical import JointMapping

FOOT_JOINTS: tuple[tuple[str, str], ...] = (
    ("left_toe", "LeftToeBase"), ("left_heel", "LeftFoot"), ("right_toe", "RightToeBase"), ("right_heel", "RightFoot"),
)  # fmt: skip


@dataclass(frozen=True)
class FootContactParams:
    """Thresholds at a 1.80 m character and 30 fps."""

    toe_height_m: float = 0.03
    displacement_m: float = 0.01
    reference_height_m: float = 1.80
    reference_fps: float = 30.0
    window: int = 5


@dataclass
class FootContacts:
    """labels: ``(F, 4)`` bool for (left toe, left heel, right toe, right heel); joints: the skeleton joint of
    each column or -1 when the rig lacks it (its column is then all False)."""

    labels: Tensor
    joints: list[int]
    names: tuple[str, ...] = field(default=tuple(n for n, _ in FOOT_JOINTS))

    @property
    def available(self) -> Tensor:
        """``(4,)`` bool: the columns whose joint exists."""
        return torch.tensor([j >= 0 for j in self.joints])


def fill_window(labels: Tensor, window: int = 5) -> Tensor:
    """``labels (F, C)`` with frames set where more than half of the centred ``window`` is set (fills gaps)."""
    if labels.shape[0] == 0:
        return labels
    half = window // 2
    x = labels.float().T[:, None, :]  # (C, 1, F)
    padded = torch.nn.functional.pad(x, (half, half))
    counts = torch.nn.functional.conv1d(padded, torch.ones(1, 1, window))[:, 0, :].T  # (F, C)
    return labels | (counts > window / 2)


def detect_foot_contacts(
    global_positions: Tensor,
    rest_positions: Tensor,
    mapping: JointMapping,
    height: float,
    fps: float,
    ground: float = 0.0,
    params: FootContactParams | None = None,
) -> FootContacts:
    """Foot contacts from world joint positions ``(F, J, 3)``; ``rest_positions (J, 3)`` of the rest pose
    standing on y = 0; ``height`` of the body (m); ``ground`` the floor height of the clip."""
    params = params or FootContactParams()
    scale = height / params.reference_height_m
    step = params.displacement_m * scale * params.reference_fps / fps
    f_n = global_positions.shape[0]
    labels = torch.zeros(f_n, len(FOOT_JOINTS), dtype=torch.bool)
    joints = []
    for c, (name, canonical) in enumerate(FOOT_JOINTS):
        j = mapping.joints.get(canonical, -1)
        joints.append(j)
        if j < 0 or f_n == 0:
            continue
        p = global_positions[:, j].detach()
        disp = torch.zeros(f_n)
        if f_n > 1:
            d = (p[1:] - p[:-1]).norm(dim=-1)
            disp[1:] = d
            disp[0] = d[0]
        ok = disp <= step
        if name.endswith("toe"):
            ok &= (p[:, 1] - ground - rest_positions[j, 1]) <= params.toe_height_m * scale
        labels[:, c] = ok
    return FootContacts(fill_window(labels, params.window), joints)


__all__ = ["FOOT_JOINTS", "FootContactParams", "FootContacts", "detect_foot_contacts", "fill_window"]
