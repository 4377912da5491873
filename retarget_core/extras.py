"""Extra joints beyond the 22: fingers, toes and twist bones, found by name and by the chain structure.

Mapping (after the 22 canonical joints are mapped, so the hands, feet and limbs are known):

* **Fingers** are searched below each mapped hand (a thumb also beside it, below), so their side is the hand's (a
  finger named for the other side is reported, not mapped). A joint names its finger by a finger token (``thumb``,
  ``index``, ``middle``/``mid``, ``ring``, ``pinky``/``little``) or by ``finger`` + its number (MakeHuman's
  ``finger2-1.L`` is the index); a metacarpal by ``metacarpal``/``palm`` (+ 1..4 = index..pinky when no finger token
  names it). A finger's joints are numbered along the chain from the hand: the metacarpal is segment 0
  (``LeftHandIndex0``), the next three joints segments 1..3; a fourth (Mixamo's ``LeftHandIndex4``, a tip) is not
  mapped. The thumb has no segment 0: its first joint is ``Thumb1`` in every convention (Mixamo ``Thumb1``, Unreal
  ``thumb_01``, VRM 1 ``thumbMetacarpal``, VRM 0 ``thumbProximal``). Where the hand's children carry no finger names
  at all, chains of two or more joints below the hand are taken as fingers by structure: the thumb is the chain
  whose first bone leaves the hand furthest from the mean finger direction (when it clearly does), the others are
  ordered from the thumb side (confidence 0.45, a warning says so).
* **Thumbs beside the hand**: when nothing below the hand is a thumb, thumb-named joints of that side that hang
  from the hand's parent (the forearm, or an in-chain segment below it) are the thumb, numbered the same way
  (Quaternius' ``Thumb1.L``, ``Thumb2.L`` beside ``Fist.L``; confidence 0.8, a warning says they hang from the
  forearm). The copy sets their world rotation, so they turn with the hand as the source's thumb does.
* **Mittens**: where the hand's joints carry no finger names, one chain of joints below it named like the hand
  (Quaternius' ``Fist1.L``, ``Fist2.L`` below ``Fist.L``: four fingers fused in one block) is mapped as the middle
  finger, segments 1..3, so the block curls as the source's middle finger (confidence 0.6, a warning says so, and
  another names any joint that hangs from a mitten segment, a held prop that turns with the curl).
* **Toes** likewise below each mapped foot (``BigToe1``.., from ``big toe``/``hallux`` or ``toe`` + its number),
  segments 1..3 along the chain; the joint mapped as ToeBase is never a toe segment.
* **Twist bones**: a joint named ``twist``/``roll`` below a mapped Arm, ForeArm, UpLeg or Leg and not below the
  limb's next canonical joint (Unreal ``lowerarm_twist_01_l``, Reallusion ``CC_Base_L_ForearmTwist01``), or an
  unmapped joint on the chain between two mapped limb joints whose name scores the same limb role (MakeHuman
  ``lowerarm02.L``, Rigify ``DEF-forearm.L.001``). Slots 1..3 go from the limb joint toward its end.
* **VRM**: when the file carries a VRM humanoid bone map (``VRM`` 0.x or ``VRMC_vrm`` 1.0), its finger bones win
  (method ``"vrm"``, confidence 1) and the names and structure fill the finger slots it lacks (a map without
  thumbs); its body bones are held by the canonical mapping itself (:func:`retarget_core.mapping.map_joints`).
* **Overrides**: the same file as for the canonical joints: ``{"LeftHandIndex1": "my_index_a_l"}`` (null unmaps),
  and ``{"LeftForeArmTwist1.share": 0.6}`` sets a twist bone's share.

Twist shares (:func:`default_twist_share`): a twist bone at fraction ``t`` along its limb segment (its rest
position projected on the segment from the limb joint to the next canonical joint) spreads the twist linearly:

* ForeArm / Leg twist bones take ``t`` of the hand's (foot's) twist about the segment's axis relative to the
  segment: none at the elbow, all of it at the wrist.
* Arm / UpLeg twist bones that hang beside the chain (Unreal, Reallusion) take ``-(1 - t)`` of the limb's own
  twist relative to its parent, so their world twist is ``t`` of the limb's: none at the shoulder, all at the
  elbow. Arm / UpLeg segments inside the chain (MakeHuman ``upperarm02``) take 0: they already follow the mapped
  upper segment, which carries the whole twist.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import torch
from torch import Tensor

from retarget_core import rotations as rot
from retarget_core.canonical import (
    EXTRA_JOINTS,
    FINGERS,
    TOE_SEGMENTS,
    TOES,
    TWIST_LIMBS,
    TWIST_SLOTS,
    JointMapping,
)
from retarget_core.kinematics import forward_kinematics
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton

CONF_NAME = 0.9  # a finger/toe named and numbered along a chain below the right hand or foot
CONF_TWIST_NAME = 0.9
CONF_TWIST_CHAIN = 0.7  # an in-chain segment named like its limb
CONF_STRUCTURE = 0.45  # fingers found from the chains alone
CONF_MITTEN = 0.6  # a mitten's segments (joints below the hand named like the hand), mapped as the middle finger
CONF_BESIDE = 0.8  # a thumb named for its side that hangs from the forearm beside the hand
THUMB_MIN_SPREAD_DEG = 25.0  # the thumb's first bone leaves the hand at least this far from the mean finger
SHARE_SUFFIX = ".share"
LIMB_END: dict[str, str] = {"Arm": "ForeArm", "ForeArm": "Hand", "UpLeg": "Leg", "Leg": "Foot"}
LIMB_PARENT: dict[str, tuple[str, ...]] = {
    "Arm": ("Shoulder",), "ForeArm": ("Arm",), "UpLeg": (), "Leg": ("UpLeg",),
}  # fmt: skip


@dataclass(frozen=True)
class _Vocab:
    compounds: dict[str, tuple[str, ...]]
    fingers: dict[str, str]
    finger_words: frozenset[str]
    metacarpal: frozenset[str]
    toes: dict[str, str]
    toe_words: frozenset[str]
    twist: frozenset[str]
    end_site: frozenset[str]  # a leaf marking a bone's end, not something carried
    vrm_segments: dict[str, int]


@lru_cache(maxsize=1)
def _vocab() -> _Vocab:
    raw = json.loads(resources.files("retarget_core").joinpath("data/mapping_aliases.json").read_text("utf-8"))
    ex = raw["extras"]
    return _Vocab(
        compounds={k: tuple(v) for k, v in ex["compounds"].items()},
        fingers=dict(ex["fingers"]),
        finger_words=frozenset(ex["finger_words"]),
        metacarpal=frozenset(ex["metacarpal_tokens"]),
        toes=dict(ex["toes"]),
        toe_words=frozenset(ex["toe_words"]),
        twist=frozenset(ex["twist_tokens"]),
        end_site=frozenset(ex["end_site_tokens"]),
        vrm_segments=dict(ex["vrm_segments"]),
    )


# ------------------------------------------------------------------------------------------------ names


@dataclass(frozen=True)
class DigitName:
    """What a joint name says about a finger or toe: which one (or None), metacarpal or not, its side."""

    digit: str | None
    metacarpal: bool
    side: str | None
    ignored: bool


def _tokens(name: str) -> list[str]:
    from retarget_core.mapping import name_tokens

    vocab = _vocab()
    return [t for tok in name_tokens(name) for t in vocab.compounds.get(tok, (tok,))]


def _numbers(tokens: list[str]) -> list[int]:
    return [int(t) for t in tokens if t.isdigit()]


def finger_name(name: str) -> DigitName:
    """The finger (``"Thumb"`` .. ``"Pinky"``) a joint name gives, if any, and whether it is a metacarpal."""
    from retarget_core.mapping import analyse_name

    vocab, info = _vocab(), analyse_name(name)
    tokens = _tokens(name)
    meta = any(t in vocab.metacarpal for t in tokens)
    named = [vocab.fingers[t] for t in tokens if t in vocab.fingers]
    nums = _numbers(tokens)
    digit = named[0] if named else None
    if digit is None and len(nums) >= 2 and any(t in vocab.finger_words for t in tokens) and 1 <= nums[0] <= 5:
        digit = FINGERS[nums[0] - 1]  # MakeHuman finger1-1 = thumb (one number alone is a segment: CMU's Finger1)
    elif digit is None and meta and nums and 1 <= nums[0] <= 4:
        digit = FINGERS[nums[0]]  # MakeHuman metacarpal1 = index, rigify palm.01 = index
    elif digit is None and re.match(r"bip\d*[ _]", name.split(":")[-1], re.IGNORECASE):
        digit = _biped_finger(tokens)
    if any(t in vocab.toe_words for t in tokens):
        digit = None  # a toe, not a finger
    return DigitName(digit, meta, info.side, info.ignored)


def _biped_finger(tokens: list[str]) -> str | None:
    """3ds Max Biped: ``Finger0``, ``Finger01``, ``Finger02`` are the thumb's joints, ``Finger1..`` the index's."""
    if "finger" not in tokens:
        return None
    at = tokens.index("finger")
    number = tokens[at + 1] if at + 1 < len(tokens) else ""
    return FINGERS[int(number[0])] if number.isdigit() and int(number[0]) < 5 else None


def toe_name(name: str) -> DigitName:
    """The toe (``"BigToe"`` .. ``"PinkyToe"``) a joint name gives, if any."""
    from retarget_core.mapping import analyse_name

    vocab, info = _vocab(), analyse_name(name)
    tokens = _tokens(name)
    if not any(t in vocab.toe_words for t in tokens) and "hallux" not in tokens:
        return DigitName(None, False, info.side, info.ignored)
    named = [vocab.toes[t] for t in tokens if t in vocab.toes]
    nums = _numbers(tokens)
    digit = named[0] if named else None
    if digit is None and nums and 1 <= nums[0] <= 5 and len(nums) >= 2:
        digit = TOES[nums[0] - 1]  # MakeHuman toe1-1 = big toe (one number alone is a segment: 'Toe1')
    return DigitName(digit, False, info.side, info.ignored)


def is_twist_name(name: str) -> bool:
    """A twist/roll bone by name (share/corrective bones are not)."""
    return any(t in _vocab().twist for t in _tokens(name))


# ------------------------------------------------------------------------------------------------ mapping


@dataclass
class _Found:
    """One extra joint found: joint index, confidence, method."""

    joint: int
    conf: float
    method: str


class _ExtraMapper:
    """One run of the extra-joint mapping on a skeleton whose canonical joints are mapped."""

    def __init__(self, skeleton: Skeleton, mapping: JointMapping) -> None:
        self.sk, self.map = skeleton, mapping
        self.n = skeleton.num_joints
        self.children: list[list[int]] = [[] for _ in range(self.n)]
        for j, p in enumerate(skeleton.parents):
            if p >= 0:
                self.children[p].append(j)
        self.depth = [0] * self.n
        for j, p in enumerate(skeleton.parents):
            self.depth[j] = self.depth[p] + 1 if p >= 0 else 0
        self.pos = skeleton.rest_global()[1].double()
        self.used = set(mapping.joints.values())
        self.found: dict[str, _Found] = {}
        self.in_chain: set[str] = set()  # twist slots lying on the limb chain
        self.warnings: list[str] = []

    def below(self, top: int, through_used: bool = False) -> list[int]:
        """Joints under ``top`` (excluded) that are not canonical joints, in index order; the search stops at
        canonical joints unless ``through_used`` (toes below the ToeBase joint)."""
        out, stack = [], list(self.children[top])
        while stack:
            j = stack.pop()
            if j in self.used and not through_used:
                continue
            if j not in self.used:
                out.append(j)
            stack.extend(self.children[j])
        return sorted(out)

    def is_ancestor(self, a: int, b: int) -> bool:
        p = self.sk.parents[b]
        while p >= 0:
            if p == a:
                return True
            p = self.sk.parents[p]
        return False

    def put(self, name: str, joint: int, conf: float, method: str) -> None:
        self.found[name] = _Found(joint, conf, method)

    def warn(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)

    # ---------------------------------------------------------------- fingers and toes

    def digits_by_name(
        self, side: str, top: int, reader: Callable[[str], DigitName] = finger_name
    ) -> dict[str, list[tuple[int, DigitName]]]:
        """Joints below ``top`` grouped by the finger (or toe) ``reader`` reads in their names, each by depth."""
        groups: dict[str, list[tuple[int, DigitName]]] = {}
        for j in self.below(top, through_used=reader is toe_name):
            dn = reader(self.sk.names[j])
            if dn.digit is None or dn.ignored:
                continue
            if dn.side not in (None, side):
                self.warn(f"{self.sk.names[j]!r} is named for the other side but hangs below the {side.lower()} "
                          "hand or foot: not mapped")  # fmt: skip
                continue
            groups.setdefault(dn.digit, []).append((j, dn))
        for g in groups.values():
            g.sort(key=lambda jd: (self.depth[jd[0]], jd[0]))
        return groups

    def map_fingers(self, side: str, hand: int) -> None:
        """Fingers by name below the hand, else a mitten, else by structure; then a thumb beside the hand."""
        groups = self.digits_by_name(side, hand)
        if groups:
            for finger, joints in groups.items():
                metas = [j for j, dn in joints if dn.metacarpal] if finger != "Thumb" else []
                if metas:
                    self.put(f"{side}Hand{finger}0", metas[0], CONF_NAME, "name")
                self.put_segments(f"{side}Hand{finger}", [j for j, _ in joints if j not in metas], CONF_NAME)
        elif not self.mitten(side, hand):
            self.fingers_by_structure(side, hand)
        if not any(n.startswith(f"{side}HandThumb") for n in self.found):
            self.thumb_beside_hand(side, hand)

    def put_segments(self, prefix: str, joints: list[int], conf: float) -> list[str]:
        """Number ``joints`` (sorted by depth) 1..3 (:data:`TOE_SEGMENTS`, the fingers' too) by tree distance from
        the first, a skipped joint leaving a gap; returns the names put."""
        names = []
        for j in joints:
            k = self.depth[j] - self.depth[joints[0]] + 1
            if k in TOE_SEGMENTS:
                self.put(f"{prefix}{k}", j, conf, "name")
                names.append(f"{prefix}{k}")
        return names

    def mitten(self, side: str, hand: int) -> bool:
        """A mitten: one chain of joints below the hand named like the hand and for no finger (Quaternius
        ``Fist1.L``, ``Fist2.L`` below ``Fist.L``), the four fingers fused in one block. Its segments are mapped
        as the middle finger's, so the block curls as the source's middle finger does."""
        from retarget_core.mapping import analyse_name

        joints = []
        for j in self.below(hand):
            info = analyse_name(self.sk.names[j])
            plain = not (info.ignored or info.helper or info.finger) and info.side in (None, side)
            if plain and info.scores.get("Hand", 0.0) > 0.0 and finger_name(self.sk.names[j]).digit is None:
                joints.append(j)
        joints.sort(key=lambda j: (self.depth[j], j))
        if not joints or not all(self.is_ancestor(a, b) for a, b in zip(joints, joints[1:], strict=False)):
            return False  # none, or branching: not one fused block
        names = self.put_segments(f"{side}HandMiddle", joints, CONF_MITTEN)
        listed = ", ".join(repr(self.sk.names[j]) for j in joints)
        self.warn(f"the {side.lower()} hand is a mitten ({listed}: one block of four fingers): mapped as "
                  f"{', '.join(names)}, it curls as the source's middle finger")  # fmt: skip
        for name, j in zip(names, joints, strict=False):
            for c in self.children[j]:
                if c not in joints and not _vocab().end_site & set(_tokens(self.sk.names[c])):
                    prop, seg = self.sk.names[c], self.sk.names[j]
                    self.warn(f"{prop!r} (a held prop?) hangs from {seg!r}, mapped as {name}: it turns with the "
                              f"mitten's curl; override {name} to null to hold it still")  # fmt: skip
        return True

    def thumb_beside_hand(self, side: str, hand: int) -> None:
        """Thumb joints hanging from the hand's parent (the forearm, or a segment below it) beside the hand, not
        below it (Quaternius' mitten rigs), mapped as the side's thumb when the hand has none below it."""
        parent = self.sk.parents[hand]
        fore = self.map.joints.get(side + "ForeArm")
        if parent < 0 or fore is None or (parent != fore and not self.is_ancestor(fore, parent)):
            return
        thumbs, taken = [], self.found_joints()
        for j in self.below(parent):  # stops at canonical joints: never inside the hand, nor another limb
            dn = finger_name(self.sk.names[j])
            if dn.digit == "Thumb" and not dn.ignored and dn.side in (None, side) and j not in taken:
                thumbs.append(j)
        if not thumbs:
            return
        thumbs.sort(key=lambda j: (self.depth[j], j))
        names = self.put_segments(f"{side}HandThumb", thumbs, CONF_BESIDE)
        self.warn(f"{', '.join(repr(self.sk.names[j]) for j in thumbs)} hang from the forearm "
                  f"{self.sk.names[parent]!r}, beside the {side.lower()} hand, not below it: mapped as "
                  f"{', '.join(names)} (they turn with the source's thumb, set in world space)")  # fmt: skip

    def found_joints(self) -> set[int]:
        """Joints already mapped as extras."""
        return {f.joint for f in self.found.values()}

    def chain(self, start: int) -> list[int]:
        """``start`` and the joints below it while each has exactly one child."""
        out = [start]
        while len(self.children[out[-1]]) == 1:
            out.append(self.children[out[-1]][0])
        return out

    def fingers_by_structure(self, side: str, hand: int) -> None:
        """Unnamed chains of two or more joints below the hand: the thumb by its spread, the rest from its side."""
        chains = [self.chain(c) for c in self.children[hand] if c not in self.used]
        chains = [c for c in chains if len(c) >= 2]
        if len(chains) < 2:
            return
        dirs = torch.stack([self.pos[c[1]] - self.pos[c[0]] for c in chains])
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp(min=1e-9)
        mean = dirs.mean(0)
        mean = mean / mean.norm().clamp(min=1e-9)
        spread = torch.rad2deg(torch.arccos((dirs @ mean).clamp(-1.0, 1.0)))
        thumb = int(spread.argmax())
        if float(spread[thumb]) < THUMB_MIN_SPREAD_DEG:
            self.warn(f"the {side.lower()} hand's {len(chains)} unnamed finger chains show no thumb: not mapped")
            return
        roots = torch.stack([self.pos[c[0]] for c in chains])
        lateral = roots - roots[thumb]
        lateral = lateral - (lateral @ mean)[:, None] * mean
        order = sorted((k for k in range(len(chains)) if k != thumb), key=lambda k: float(lateral[k].norm()))
        for finger, k in zip(FINGERS, [thumb, *order], strict=False):
            for s, j in enumerate(chains[k][:3], start=1):
                self.put(f"{side}Hand{finger}{s}", j, CONF_STRUCTURE, "structure")
        self.warn(f"the {side.lower()} hand's fingers have no names: taken from the chains' layout (thumb by its "
                  "spread, then index to pinky from the thumb side)")  # fmt: skip

    def map_toes(self, side: str, foot: int) -> None:
        for toe, joints in self.digits_by_name(side, foot, toe_name).items():
            self.put_segments(f"{side}Foot{toe}", [j for j, _ in joints], CONF_NAME)

    # ---------------------------------------------------------------- twist bones

    def fraction(self, limb_joint: int, end: int | None, j: int) -> float:
        """Where joint ``j`` lies along the segment from ``limb_joint`` to ``end``, 0..1 (0.5 without an end)."""
        if end is None:
            return 0.5
        seg = self.pos[end] - self.pos[limb_joint]
        length2 = float(seg @ seg)
        if length2 < 1e-12:
            return 0.5
        return float(min(1.0, max(0.0, float((self.pos[j] - self.pos[limb_joint]) @ seg) / length2)))

    def map_twists(self, side: str, limb: str) -> dict[str, float]:
        """Twist bones of one limb segment; returns their fractions along it."""
        from retarget_core.mapping import analyse_name

        top = self.map.joints.get(side + limb)
        if top is None:
            return {}
        end = self.map.joints.get(side + LIMB_END[limb])
        cands: list[tuple[int, bool, float]] = []  # joint, in chain, confidence
        for j in range(top + 1, self.n):
            if j in self.used or not self.is_ancestor(top, j) or (end is not None and self.is_ancestor(end, j)):
                continue
            info = analyse_name(self.sk.names[j])
            if info.ignored or info.side not in (None, side):
                continue
            in_chain = end is not None and self.is_ancestor(j, end)
            if is_twist_name(self.sk.names[j]):
                cands.append((j, in_chain, CONF_TWIST_NAME))
            elif in_chain and info.scores.get(limb, 0.0) > 0:
                cands.append((j, True, CONF_TWIST_CHAIN))
        cands.sort(key=lambda c: (self.fraction(top, end, c[0]), c[0]))
        if len(cands) > len(TWIST_SLOTS):
            self.warn(f"{side}{limb} has {len(cands)} twist bones: only the first {len(TWIST_SLOTS)} are driven")
        fractions: dict[str, float] = {}
        for slot, (j, in_chain, conf) in zip(TWIST_SLOTS, cands, strict=False):
            name = f"{side}{limb}Twist{slot}"
            self.put(name, j, conf, "name" if conf == CONF_TWIST_NAME else "structure")
            fractions[name] = self.fraction(top, end, j)
            if in_chain:
                self.in_chain.add(name)
        return fractions


def split_twist(name: str) -> tuple[str, str]:
    """``"LeftForeArmTwist1"`` -> ``("Left", "ForeArm")``."""
    match = re.fullmatch(r"(Left|Right)(\w+?)Twist\d", name)
    if match is None:
        raise ValueError(f"{name!r} is not a twist joint")
    return match.group(1), match.group(2)


def default_twist_share(limb: str, fraction: float, in_chain: bool) -> float:
    """The share of its limb's twist a twist bone takes (see the module doc)."""
    if limb in ("ForeArm", "Leg"):
        return fraction
    return 0.0 if in_chain else -(1.0 - fraction)


def split_override(override: dict[str, object] | None) -> tuple[dict[str, str | None], dict[str, float]]:
    """The extra-joint entries of an override (extra name -> joint name or None) and its twist shares."""
    joints: dict[str, str | None] = {}
    shares: dict[str, float] = {}
    for key, value in (override or {}).items():
        if key.endswith(SHARE_SUFFIX) and key[: -len(SHARE_SUFFIX)] in EXTRA_JOINTS:
            shares[key[: -len(SHARE_SUFFIX)]] = float(value)  # type: ignore[arg-type]
        elif key in EXTRA_JOINTS:
            joints[key] = value  # type: ignore[assignment]
    return joints, shares


def _apply_vrm(m: _ExtraMapper, vrm: dict[str, str]) -> None:
    """The VRM humanoid bone map's fingers replace the name-and-structure ones of the same slot or joint; the
    names and structure keep the slots the map lacks."""
    for c, joint_name in vrm.items():
        if c in m.map.joints and m.sk.find(joint_name) not in (None, m.map.joints[c]):
            m.warn(f"{c}: the VRM humanoid map says {joint_name!r}, the names and structure gave "
                   f"{m.sk.names[m.map.joints[c]]!r} (kept; override it if the VRM map is right)")  # fmt: skip
    by_side: dict[str, dict[str, int]] = {}
    for extra, joint_name in vrm.items():
        j = m.sk.find(joint_name)
        if j is not None and extra in EXTRA_JOINTS:
            by_side.setdefault("Left" if extra.startswith("Left") else "Right", {})[extra] = j
    for side, bones in by_side.items():
        kept = []
        for name in [n for n in m.found if n.startswith(f"{side}Hand")]:
            if name in bones and bones[name] != m.found[name].joint:
                m.warn(f"{name}: the VRM humanoid map says {m.sk.names[bones[name]]!r}, the names said "
                       f"{m.sk.names[m.found[name].joint]!r} (the VRM map is used)")  # fmt: skip
            if name in bones or m.found[name].joint in bones.values():
                del m.found[name]
            else:
                kept.append(name)
        for name, j in bones.items():
            m.put(name, j, 1.0, "vrm")
        if kept:  # a partial VRM map (no thumb, no distal joint): the names fill what it lacks
            m.warn(f"the VRM humanoid map has no {', '.join(kept)}: taken from the names and structure")


def _apply_override(m: _ExtraMapper, joints: dict[str, str | None]) -> None:
    for name, joint_name in joints.items():
        m.found.pop(name, None)
        if joint_name is None:
            continue
        j = m.sk.index(joint_name)
        for other in [n for n, f in m.found.items() if f.joint == j]:
            del m.found[other]
        m.put(name, j, 1.0, "override")


def _drop_duplicates(m: _ExtraMapper) -> None:
    best: dict[int, str] = {}
    for name, f in m.found.items():
        keep = best.get(f.joint)
        if keep is None or (f.conf, f.method == "override") > (m.found[keep].conf, m.found[keep].method == "override"):
            best[f.joint] = name
    for name in [n for n, f in m.found.items() if best[f.joint] != n]:
        m.warn(
            f"{name} ({m.sk.names[m.found[name].joint]!r}) dropped: the joint is already {best[m.found[name].joint]}"
        )
        del m.found[name]


def map_extras(
    skeleton: Skeleton,
    mapping: JointMapping,
    override: dict[str, object] | None = None,
    vrm: dict[str, str] | None = None,
) -> None:
    """Find the fingers, toes and twist bones of ``skeleton`` and store them in ``mapping`` (its ``extras``,
    ``extra_confidence``, ``extra_method``, ``twist_share`` and warnings). ``override``: the mapping override (its
    extra-joint and ``.share`` entries are used, joint names already checked); ``vrm``: extra name -> joint name
    from the file's VRM humanoid bone map."""
    m = _ExtraMapper(skeleton, mapping)
    fractions: dict[str, float] = {}
    for side in ("Left", "Right"):
        if (hand := mapping.joints.get(side + "Hand")) is not None:
            m.map_fingers(side, hand)
        if (foot := mapping.joints.get(side + "Foot")) is not None:
            m.map_toes(side, foot)
        for limb in TWIST_LIMBS:
            fractions.update(m.map_twists(side, limb))
    if vrm:
        _apply_vrm(m, vrm)
    joints, shares = split_override(override)
    _apply_override(m, joints)
    _drop_duplicates(m)
    ordered = [n for n in EXTRA_JOINTS if n in m.found]
    mapping.extras = {n: m.found[n].joint for n in ordered}
    mapping.extra_confidence = {n: round(m.found[n].conf, 4) for n in ordered}
    mapping.extra_method = {n: m.found[n].method for n in ordered}
    mapping.twist_share = {}
    for n in ordered:
        if "Twist" not in n:
            continue
        side, limb = split_twist(n)
        mapping.twist_share[n] = shares.get(n, default_twist_share(limb, fractions.get(n, 0.5), n in m.in_chain))
    mapping.warnings.extend(w for w in m.warnings if w not in mapping.warnings)


# ------------------------------------------------------------------------------------------------ transfer

MIN_BONE_LENGTH_M = 1e-4


def _digit_parts(name: str) -> tuple[str, str, str, int]:
    """``"LeftHandIndex1"`` -> ``("Left", "Hand", "Index", 1)``; ``"LeftFootBigToe2"`` -> ``("Left", "Foot", "BigToe", 2)``."""
    match = re.fullmatch(r"(Left|Right)(Hand|Foot)(\w+?)(\d)", name)
    if match is None:
        raise ValueError(f"{name!r} is not a finger or toe joint")
    return match.group(1), match.group(2), match.group(3), int(match.group(4))


def _source_digit(side: str, part: str, digit: str, seg: int, source_map: JointMapping) -> str | None:
    """The source extra that drives a target finger or toe: the same one, or for a digit the source lacks
    entirely, the same segment of its nearest digit (never another finger for the thumb or a metacarpal)."""
    same = f"{side}{part}{digit}{seg}"
    if same in source_map.extras:
        return same
    order = FINGERS if part == "Hand" else TOES
    present = [d for d in order if any(n.startswith(f"{side}{part}{d}") and n[len(side + part + d) :].isdigit()
                                       for n in source_map.extras)]  # fmt: skip
    if digit in present or seg == 0 or digit == "Thumb":
        return None
    candidates = [d for d in present if d != "Thumb"]
    if not candidates:
        return None
    nearest = min(candidates, key=lambda d: (abs(order.index(d) - order.index(digit)), order.index(d)))
    name = f"{side}{part}{nearest}{seg}"
    return name if name in source_map.extras else None


def digit_pairs(source_map: JointMapping, target_map: JointMapping) -> dict[str, str]:
    """Target finger/toe extra -> the source extra that drives it (see :func:`_source_digit`)."""
    pairs: dict[str, str] = {}
    for name in target_map.extras:
        if "Twist" in name:
            continue
        side, part, digit, seg = _digit_parts(name)
        src = _source_digit(side, part, digit, seg, source_map)
        if src is not None:
            pairs[name] = src
    return pairs


def transfer_notes(source_map: JointMapping, target_map: JointMapping) -> list[str]:
    """What the copy does with the target's extra joints, for the job's warnings: substituted fingers, fingers
    left at rest, twist bones driven."""
    pairs = digit_pairs(source_map, target_map)
    notes: list[str] = []
    subs = sorted({(t[:-1], s[:-1]) for t, s in pairs.items() if t[:-1] != s[:-1]})
    if subs:
        notes.append("the source lacks some fingers or toes: " + ", ".join(f"{t} follows {s}" for t, s in subs))
    for side in ("Left", "Right"):
        for part, what in (("Hand", "fingers"), ("Foot", "toes")):
            tgt = [n for n in target_map.extras if n.startswith(side + part) and "Twist" not in n]
            if tgt and not any(n in pairs for n in tgt):
                notes.append(f"the source has no {side.lower()} {what}: the target's stay in their rest pose")
            elif rest := [n for n in tgt if n not in pairs]:
                notes.append(f"not driven by the source (kept at rest relative to their parent): {', '.join(rest)}")
    return notes


def _bone_direction(name: str, extras: dict[str, int], sk: Skeleton, pos: Tensor) -> Tensor | None:
    """Rest direction ``(3,)`` of a finger/toe joint: toward its next mapped segment, else its longest child."""
    side, part, digit, seg = _digit_parts(name)
    j = extras[name]
    nxt = extras.get(f"{side}{part}{digit}{seg + 1}")
    ends = [nxt] if nxt is not None else sorted(sk.children(j), key=lambda c: -float((pos[c] - pos[j]).norm()))
    for e in ends:
        d = pos[e] - pos[j]
        if float(d.norm()) > MIN_BONE_LENGTH_M:
            return d
    return None


def digit_line(side: str, part: str, extras: dict[str, int], pos: Tensor) -> Tensor | None:
    """The knuckle line ``(3,)`` of a hand (foot) at rest: from the first joint of its last digit (pinky side) to
    that of its first non-thumb digit (index side); None with fewer than two such digits."""
    order = FINGERS[1:] if part == "Hand" else TOES
    firsts = []
    for digit in order:
        first = next((extras[n] for k in (1, 0, 2) if (n := f"{side}{part}{digit}{k}") in extras), None)
        if first is not None:
            firsts.append(first)
    if len(firsts) < 2:
        return None
    line = pos[firsts[0]] - pos[firsts[-1]]
    return line if float(line.norm()) > MIN_BONE_LENGTH_M else None


def _frame(d: Tensor, line: Tensor | None) -> Tensor | None:
    """A rest frame ``(4,)``: y along the bone ``d``, x toward the knuckle line; None when they are parallel."""
    if line is None:
        return None
    dn, ln = d / d.norm(), line / line.norm()
    if float(torch.linalg.cross(dn, ln).norm()) < 0.1:
        return None
    return rot.from_frame(d, line, primary_axis=1, secondary_axis=0)


def digit_alignment(
    source: Skeleton, source_map: JointMapping, target: Skeleton, target_map: JointMapping, align: dict[str, Tensor]
) -> dict[str, tuple[int, int, Tensor]]:
    """Per driven target finger/toe: (source joint, target joint, world alignment ``A (4,)``).

    ``A`` takes the target's rest frame of the bone onto the source's, each frame made of the bone direction and
    the hand's knuckle line (:func:`digit_line`): a finger curled about its knuckles at rest is uncurled exactly,
    with no roll. Without a knuckle line on both sides (fewer than two fingers), ``A`` is the previous segment's
    (or the hand's, from ``align``) followed by the shortest arc of the bone. A bone without a direction (a last
    segment with no child) takes the previous segment's ``A``."""
    _, spos = source.rest_global()
    _, tpos = target.rest_global()
    out: dict[str, tuple[int, int, Tensor]] = {}
    pairs = digit_pairs(source_map, target_map)
    lines: dict[tuple[str, str], tuple[Tensor | None, Tensor | None]] = {}
    for name in sorted(pairs, key=lambda n: (n[:-1], int(n[-1]))):  # segments in chain order
        side, part, digit, seg = _digit_parts(name)
        if (side, part) not in lines:
            lines[side, part] = (digit_line(side, part, source_map.extras, spos),
                                 digit_line(side, part, target_map.extras, tpos))  # fmt: skip
        prev = next((n for k in range(seg - 1, -1, -1) if (n := f"{side}{part}{digit}{k}") in out), None)
        base = out[prev][2] if prev is not None else align.get(side + part, torch.tensor([0.0, 0.0, 0.0, 1.0]))
        ds = _bone_direction(pairs[name], source_map.extras, source, spos)
        dt = _bone_direction(name, target_map.extras, target, tpos)
        a = base
        if ds is not None and dt is not None:
            fs, ft = _frame(ds, lines[side, part][0]), _frame(dt, lines[side, part][1])
            if fs is not None and ft is not None:
                a = rot.normalize(rot.mul(fs, rot.inv(ft)))
            else:
                a = rot.normalize(rot.mul(rot.between(rot.apply(base, dt.to(base.dtype)), ds.to(base.dtype)), base))
        out[name] = (source_map.extras[pairs[name]], target_map.extras[name], a)
    return out


def digit_world_rotations(
    s_rot: Tensor, s_rest_rot: Tensor, t_rest_rot: Tensor, alignment: dict[str, tuple[int, int, Tensor]]
) -> dict[int, Tensor]:
    """Target joint -> desired world rotation ``(F, 4)``: ``Q_s(t) Q_s_rest^-1 A Q_t_rest`` as for the body.
    s_rot: ``(F, J_s, 4)`` source world rotations; s_rest_rot, t_rest_rot: ``(J, 4)`` rest world rotations."""
    out: dict[int, Tensor] = {}
    for sj, tj, a in alignment.values():
        delta = rot.mul(s_rot[:, sj], rot.inv(s_rest_rot[sj]))
        out[tj] = rot.normalize(rot.mul(rot.mul(delta, a.to(delta.dtype)), t_rest_rot[tj]))
    return out


def twist_angle(q: Tensor, axis: Tensor) -> Tensor:
    """Angle ``(F,)`` (radians, in (-pi, pi]) of the twist of ``q (F, 4)`` about the unit ``axis (3,)`` in the
    swing-twist split ``q = swing * twist``."""
    proj = (q[..., :3] * axis).sum(-1)
    angle = 2.0 * torch.atan2(proj, q[..., 3])
    return torch.remainder(angle + torch.pi, 2 * torch.pi) - torch.pi


def about_axis(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotations ``(F, 4)`` by ``angle (F,)`` radians about the unit ``axis (3,)``."""
    half = 0.5 * angle
    return torch.cat([torch.sin(half)[:, None] * axis, torch.cos(half)[:, None]], -1)


@dataclass(frozen=True)
class TwistDriver:
    """How one twist bone of the target follows its limb (see the module doc).

    limb: the limb joint (Arm, ForeArm, UpLeg or Leg); end: its next canonical joint (ForeArm, Hand, Leg, Foot).
    own: True for Arm/UpLeg (the limb's own twist relative to its parent), False for ForeArm/Leg (the end
    joint's twist relative to the limb). axis: ``(3,)`` the limb's bone axis in the limb's local frame.
    share: the share of that twist the bone takes. offset: ``(4,)`` the bone's rest rotation in the limb's frame.
    end_rest: ``(4,)`` the end joint's rest rotation in the limb's frame.
    """

    limb: int
    end: int
    own: bool
    axis: Tensor
    share: float
    offset: Tensor
    end_rest: Tensor

    def world(self, world: list[Tensor], local_r: Tensor, desired: dict[int, Tensor], rest_local: Tensor) -> Tensor:
        """The bone's world rotation ``(F, 4)`` from the limb's world and local rotations already computed
        (``world[j]`` ``(F, 4)``, ``local_r`` ``(F, J, 4)``) and the end joint's desired world rotation."""
        w_limb = world[self.limb]
        if self.own:
            q = rot.mul(rot.inv(rest_local[self.limb]), local_r[:, self.limb])
        elif self.end in desired:
            q = rot.mul(rot.mul(rot.inv(w_limb), desired[self.end]), rot.inv(self.end_rest))
        else:
            q = rot.identity(w_limb.shape[0], dtype=w_limb.dtype)
        turn = about_axis(self.axis.to(q.dtype), self.share * twist_angle(q, self.axis.to(q.dtype)))
        return rot.normalize(rot.mul(rot.mul(w_limb, turn), self.offset.to(q.dtype)))


def twist_drivers(target: Skeleton, target_map: JointMapping) -> dict[int, TwistDriver]:
    """Target joint -> its :class:`TwistDriver`, for the mapped twist bones with a non-zero share whose limb and
    end joints are mapped."""
    grot, gpos = target.rest_global()
    out: dict[int, TwistDriver] = {}
    for name, j in target_map.extras.items():
        share = target_map.twist_share.get(name, 0.0)
        if "Twist" not in name or share == 0.0:
            continue
        side, limb = split_twist(name)
        top, end = target_map.joints.get(side + limb), target_map.joints.get(side + LIMB_END[limb])
        if top is None or end is None:
            continue
        axis = rot.apply(rot.inv(grot[top]), gpos[end] - gpos[top])
        if float(axis.norm()) < MIN_BONE_LENGTH_M:
            continue
        offset = rot.mul(rot.inv(grot[top]), grot[j])
        end_rest = rot.mul(rot.inv(grot[top]), grot[end])
        out[j] = TwistDriver(top, end, limb in ("Arm", "UpLeg"), axis / axis.norm(), share, offset, end_rest)
    return out


def refresh_twists(motion: Motion, mapping: JointMapping) -> Motion:
    """``motion`` with its twist bones re-driven from its own limbs (after a stage changed the arms or legs):
    every other joint keeps its world rotation (a twist segment inside the chain passes its change on to no one).
    Returns ``motion`` itself when the rig has no driven twist bone."""
    drivers = twist_drivers(motion.skeleton, mapping)
    if not drivers:
        return motion
    parents = motion.skeleton.parents
    world, _ = forward_kinematics(parents, motion.rotations, motion.translations)
    rest_local = motion.skeleton.rest_rotations
    wanted = {j: world[:, j] for j in range(len(parents))}
    for j, d in drivers.items():
        wanted[j] = d.world([world[:, k] for k in range(len(parents))], motion.rotations, wanted, rest_local)
    local = motion.rotations.clone()
    for j, p in enumerate(parents):
        if p >= 0 and (j in drivers or p in drivers):
            local[:, j] = rot.normalize(rot.mul(rot.inv(wanted[p]), wanted[j]))
    return Motion(motion.skeleton, motion.fps, local, motion.translations, motion.name)
