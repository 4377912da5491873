"""Skeleton: joint names, parents and the rest pose as local transforms."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from retarget_core import kinematics


@dataclass(frozen=True)
class Skeleton:
    """A joint hierarchy in metres, Y up.

    names: ``(J,)`` unique joint names.
    parents: ``(J,)`` parent index of each joint, ``-1`` for roots; every parent comes before its children.
    rest_translations: ``(J, 3)`` local offset of each joint in its parent's frame (roots: world position).
    rest_rotations: ``(J, 4)`` local rotation ``xyzw`` of each joint in its rest pose.
    """

    names: list[str]
    parents: list[int]
    rest_translations: Tensor
    rest_rotations: Tensor
    _index: dict[str, int] = field(init=False, repr=False, compare=False)
    _rest_cache: dict[tuple[int, ...], tuple[Tensor, Tensor]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(set(self.names)) != len(self.names):
            raise ValueError("joint names must be unique")
        if len(self.parents) != len(self.names):
            raise ValueError("one parent per joint is needed")
        for j, p in enumerate(self.parents):
            if p >= j:
                raise ValueError(f"joint {self.names[j]!r} comes before its parent")
        object.__setattr__(self, "_index", {n: i for i, n in enumerate(self.names)})
        object.__setattr__(self, "_rest_cache", {})

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """The index of joint ``name`` (KeyError if absent)."""
        return self._index[name]

    def find(self, name: str) -> int | None:
        """The index of joint ``name`` or None."""
        return self._index.get(name)

    def children(self, joint: int) -> list[int]:
        """Indices of the direct children of ``joint``."""
        return [j for j, p in enumerate(self.parents) if p == joint]

    def ancestors(self, joint: int) -> list[int]:
        """Indices from ``joint``'s parent up to the root."""
        out = []
        p = self.parents[joint]
        while p >= 0:
            out.append(p)
            p = self.parents[p]
        return out

    def rest_global(self) -> tuple[Tensor, Tensor]:
        """World rotations ``(J, 4)`` and positions ``(J, 3)`` of the rest pose (computed once per rest pose:
        callers get their own copies)."""
        r, t = self.rest_rotations, self.rest_translations
        if r.requires_grad or t.requires_grad:  # a rest pose being optimised: differentiable, not cached
            return kinematics.forward_kinematics(self.parents, r, t)
        key = (id(r), r._version, id(t), t._version)  # a rest tensor changed in place is computed again
        if key not in self._rest_cache:
            self._rest_cache.clear()
            with torch.no_grad():
                self._rest_cache[key] = kinematics.forward_kinematics(self.parents, r.detach(), t.detach())
        grot, gpos = self._rest_cache[key]
        return grot.clone(), gpos.clone()

    def subset(self, keep: list[int]) -> Skeleton:
        """A skeleton of the joints ``keep`` (sorted, parent-closed after re-parenting to the nearest kept
        ancestor); rest transforms are recomputed so world rest positions and rotations are unchanged."""
        keep = sorted(keep)
        new_index = {old: new for new, old in enumerate(keep)}
        grot, gpos = self.rest_global()
        parents = []
        for j in keep:
            p = self.parents[j]
            while p >= 0 and p not in new_index:
                p = self.parents[p]
            parents.append(new_index[p] if p >= 0 else -1)
        rot, trans = kinematics.global_to_local(parents, grot[keep], gpos[keep])
        return Skeleton([self.names[j] for j in keep], parents, trans, rot)

    def with_rest(self, rest_rotations: Tensor, rest_translations: Tensor | None = None) -> Skeleton:
        """The same hierarchy with another rest pose."""
        return Skeleton(
            list(self.names),
            list(self.parents),
            self.rest_translations.clone() if rest_translations is None else rest_translations,
            rest_rotations,
        )


__all__ = ["Skeleton"]


def subtree(parents: list[int], joint: int) -> list[int]:
    """``joint`` and every joint below it, in skeleton order (parents before children)."""
    out = {joint}
    for j in range(joint + 1, len(parents)):
        if parents[j] in out:
            out.add(j)
    return sorted(out)
