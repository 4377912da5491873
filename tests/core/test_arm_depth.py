"""The arms' judged depth counts what the judge counts: a point inside a closed part whose nearest surface is
one of the part's caps entered through the cap and is not counted (ACCEPTANCE.md); one nearest the part's own
skin is. Checked on an open tube closed by fans, against a brute-force nearest triangle."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch

from retarget_core.contacts.arm_depth import through_cap
from retarget_core.geometry.closest_point import closest_points
from retarget_core.metrics.acceptance_body import _close_part


def _tube(n: int = 16, radius: float = 0.1, length: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """An open tube along z: ``(2n, 3)`` vertices, ``(2n, 3)`` triangles (no caps)."""
    a = np.arange(n) * 2 * math.pi / n
    ring = np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros(n)], axis=1)
    vertices = np.concatenate([ring, ring + [0.0, 0.0, length]])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]
    return vertices, np.array(faces)


def _nearest_face(local: torch.Tensor, faces: np.ndarray, p: torch.Tensor) -> torch.Tensor:
    """``(Q,)`` the nearest triangle of ``faces`` on ``local (N, 3)`` to each point ``p (Q, 3)`` (brute force)."""
    tri = torch.from_numpy(faces)
    a, b, c = (local[tri[:, i]] for i in range(3))
    out = []
    for q in p:
        d = (closest_points(q.expand(len(tri), 3), a, b, c) - q).norm(dim=-1)
        out.append(int(d.argmin()))
    return torch.tensor(out)


def test_a_point_nearest_a_cap_entered_through_it_and_one_nearest_the_skin_did_not() -> None:
    vertices, faces = _tube()
    closed = _close_part("torso", vertices, faces)
    posed = torch.from_numpy(vertices).double()[None]
    pp = SimpleNamespace(rb=SimpleNamespace(body=SimpleNamespace(part=lambda name: closed)), posed=posed)
    points = torch.tensor([[0.0, 0.0, 0.02], [0.0, 0.01, 0.985], [0.09, 0.0, 0.5], [0.0, -0.095, 0.03]],
                          dtype=torch.float64)  # fmt: skip
    local = torch.from_numpy(closed.posed(vertices)).double()
    face = _nearest_face(local, closed.faces, points)
    frames = torch.zeros(len(points), dtype=torch.long)
    assert through_cap(pp, "torso", frames, face, points).tolist() == [True, True, False, False]  # type: ignore[arg-type]
    none_found = torch.full((len(points),), -1, dtype=torch.long)
    assert not through_cap(pp, "torso", frames, none_found, points).any()  # type: ignore[arg-type]
