"""Per-vertex penetration depths of a clip, ``(F, V)``, kept as their nonzero entries.

Most vertices penetrate nothing in most frames, so the measures keep only the nonzero depths: memory grows with
the penetrating vertices, not with frames x vertices (a dense ``(F, V)`` float array is 380 MB for 1,000 frames
of a 95k-vertex character). Every figure the metrics read is a per-frame reduction computed from the entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class VertexDepths:
    """Nonzero depths of an ``(num_frames, num_vertices)`` array: ``frame``, ``vertex``, ``depth`` ``(N,)``."""

    num_frames: int
    num_vertices: int
    frame: Tensor
    vertex: Tensor
    depth: Tensor

    @classmethod
    def empty(cls, num_frames: int, num_vertices: int) -> VertexDepths:
        none = torch.zeros(0, dtype=torch.long)
        return cls(num_frames, num_vertices, none, none.clone(), torch.zeros(0))

    @classmethod
    def from_dense(cls, dense: Tensor, frames: Tensor | None = None, num_frames: int | None = None) -> VertexDepths:
        """The nonzero entries of ``dense (C, V)``, whose rows are the frames ``frames (C,)`` (default 0..C-1)."""
        rows, vertex = torch.nonzero(dense, as_tuple=True)
        frame = rows if frames is None else frames.index_select(0, rows)
        n = num_frames if num_frames is not None else dense.shape[0]
        return cls(n, dense.shape[1], frame, vertex, dense[rows, vertex])

    @staticmethod
    def concat(parts: list[VertexDepths], num_frames: int, num_vertices: int) -> VertexDepths:
        """All entries of ``parts`` (disjoint frames), ordered by frame then vertex."""
        if not parts:
            return VertexDepths.empty(num_frames, num_vertices)
        frame = torch.cat([p.frame for p in parts])
        vertex = torch.cat([p.vertex for p in parts])
        order = torch.argsort(frame * max(num_vertices, 1) + vertex)
        depth = torch.cat([p.depth for p in parts])
        return VertexDepths(num_frames, num_vertices, frame[order], vertex[order], depth[order])

    def select_frames(self, frames: Tensor) -> VertexDepths:
        """The entries of the frames ``frames`` (frame numbers kept)."""
        keep = torch.isin(self.frame, frames)
        return VertexDepths(self.num_frames, self.num_vertices, self.frame[keep], self.vertex[keep], self.depth[keep])

    def select_rows(self, keep: Tensor) -> VertexDepths:
        """The rows where ``keep (F,)`` is true, renumbered ``0..`` in order."""
        new_of = torch.cumsum(keep.long(), 0) - 1
        hit = keep.index_select(0, self.frame)
        return VertexDepths(int(keep.sum()), self.num_vertices, new_of.index_select(0, self.frame[hit]),
                            self.vertex[hit], self.depth[hit])  # fmt: skip

    def value_at(self, frame: Tensor, vertex: Tensor) -> Tensor:
        """``(N,)`` the depths at ``(frame, vertex) (N,)`` each (0 where no entry); entries ordered by frame then
        vertex, as :meth:`concat` and :meth:`from_dense` leave them."""
        keys = self.frame * self.num_vertices + self.vertex
        want = frame * self.num_vertices + vertex
        if len(keys) == 0:
            return self.depth.new_zeros(len(want))
        at = torch.searchsorted(keys, want).clamp_max(len(keys) - 1)
        return torch.where(keys[at] == want, self.depth[at], self.depth.new_zeros(()))

    def vertices_of(self, frames: Tensor) -> Tensor:
        """Sorted vertices with an entry on any of ``frames``."""
        return torch.unique(self.vertex[torch.isin(self.frame, frames)])

    def dense(self) -> Tensor:
        """The ``(F, V)`` array (for scripts and tests; the metrics never build it)."""
        out = torch.zeros(self.num_frames, self.num_vertices, dtype=self.depth.dtype)
        out[self.frame, self.vertex] = self.depth
        return out

    def frame_max(self, vertices: Tensor | None = None) -> Tensor:
        """``(F,)`` the deepest vertex of each frame (of ``vertices (N,)`` only when given; 0 when none)."""
        keep = slice(None) if vertices is None else torch.isin(self.vertex, vertices)
        out = torch.zeros(self.num_frames, dtype=self.depth.dtype)
        return out.scatter_reduce(0, self.frame[keep], self.depth[keep], "amax", include_self=True)

    def count_above(self, tolerance: float, group: Tensor | None = None, groups: int = 1) -> Tensor:
        """Vertices deeper than ``tolerance`` per frame ``(F,)``, or per frame and group ``(F, groups)`` when
        ``group (V,)`` gives each vertex's group."""
        hot = self.depth > tolerance
        f = self.frame[hot]
        if group is None:
            return torch.bincount(f, minlength=self.num_frames)
        key = f * groups + group.index_select(0, self.vertex[hot])
        return torch.bincount(key, minlength=self.num_frames * groups).view(self.num_frames, groups)

    def deepest(self, tolerance: float, per_frame: int) -> tuple[Tensor, Tensor, Tensor, bool]:
        """Per frame, the at most ``per_frame`` deepest entries deeper than ``tolerance``, frames ascending and
        depths descending: frame, vertex, depth ``(K,)``, and whether a frame had more."""
        hot = torch.nonzero(self.depth > tolerance).flatten()
        f, d = self.frame[hot], self.depth[hot]
        order = torch.argsort(d, descending=True, stable=True)
        order = order[torch.argsort(f[order], stable=True)]
        f = f[order]
        _, counts = torch.unique_consecutive(f, return_counts=True)
        rank = torch.arange(len(f)) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
        sel = hot[order][rank < per_frame]
        return self.frame[sel], self.vertex[sel], self.depth[sel], bool((counts > per_frame).any())


__all__ = ["VertexDepths"]
