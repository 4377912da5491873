"""Automatic mapping of a humanoid skeleton's joints to the 22 canonical joints.

Two sources of evidence are combined:

* **Names** (rules in ``data/mapping_aliases.json``): a name is normalised (namespace before ``:``/``|`` and one
  known rig prefix such as ``mixamorig:``, ``Bip01``, ``CC_Base_``, ``DEF-`` removed; split on separators, camel
  case and digits), its side read from tokens (``left``/``l``/``lft``, ``right``/``r``/``rt``) and each limb or
  central role scored. Twist/roll/share bones, end sites, IK/control bones and fingers are never chosen for a limb.
* **Structure**: the hands, feet and head ("anchors", named or found from the topology) fix the chains, because in
  a tree the path from a joint up to an ancestor is unique:

  - Hips = the lowest common ancestor of both feet and the chest, or its nearest ancestor with a hips-like name.
    For the Reallusion rig this is ``CC_Base_Hip`` (the root, moved by the root channels), not ``CC_Base_Pelvis``:
    the pelvis bone carries only the legs, so the spine would not be below it, breaking the canonical hierarchy.
    For a 3ds Max Biped whose thighs hang below ``Bip01 Spine`` it is ``Bip01 Pelvis``.
  - Chest = the lowest common ancestor of both hands; the joints from Hips (excluded) to the chest (included) are
    the spine chain, minus trailing neck-named joints (a Biped's clavicles hang below ``Bip01 Neck``). Spine2 is its
    last joint, Spine its first, Spine1 the joint nearest half-way along the bone lengths; with two spine joints
    Spine1 stays unmapped, with one only Spine2 is mapped. The spine names only say "spine-like": CMU's
    MotionBuilder layout ``LowerBack, Spine, Spine1`` becomes Spine, Spine1, Spine2 (a warning says so).
  - Arms (chest -> hand) and legs (Hips -> foot) are assigned by an order-preserving best match of the name scores
    along the path (so ``LeftCollar, LeftShoulder, LeftElbow`` gives clavicle, upper arm, forearm while Mixamo's
    ``LeftShoulder, LeftArm`` gives clavicle, upper arm); roles the names leave open are filled from bone lengths
    (the elbow or knee is where the two long bones are most equal), the toe from the foot's descendants.
  - Left and right come from names; only where names have no side are rest positions used (+X is left), with a
    warning and a lower confidence. Raw BVH rest poses may be nonsense, so no other decision relies on them.

Finally every mapped joint is checked to lie below its canonical parent's joint, a joint is never used twice, and
overrides (``{"LeftArm": "my_l_upperarm"}``, method ``"override"``, confidence 1) win over everything.
"""

from __future__ import annotations

import difflib
import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path

from retarget_core.canonical import CANONICAL_JOINTS, CANONICAL_PARENT, EXTRA_JOINTS, REQUIRED_JOINTS, JointMapping
from retarget_core.errors import InvalidFileError, MappingError
from retarget_core.skeleton import Skeleton

SIDES: tuple[str, str] = ("Left", "Right")
CENTRAL_ROLES: tuple[str, ...] = ("Hips", "Spine", "Neck", "Head")
LIMB_ROLES: tuple[str, ...] = ("Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot", "ToeBase")
ARM_ROLES: tuple[str, ...] = ("Shoulder", "Arm", "ForeArm", "Hand")
LEG_ROLES: tuple[str, ...] = ("UpLeg", "Leg", "Foot")

MAX_OVERRIDE_BYTES = 1024 * 1024
SHARE_SUFFIX = ".share"  # override key suffix of a twist bone's share
_LONG_BRANCH = 3  # a limb has at least this many usable joints (upper bone, lower bone, end)
_CAMEL = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")
_FORCED = 100.0  # name score of an override inside the chain matching

# Confidences of structural decisions.
CONF_STRUCTURE = 0.6  # filled between named neighbours
CONF_STRUCTURE_WEAK = 0.45  # found from the topology alone
SIDE_BY_POSITION_FACTOR = 0.6
CONTRADICTION_FACTOR = 0.5
HIERARCHY_CAP = 0.3


# ------------------------------------------------------------------------------------------------ name rules


@dataclass(frozen=True)
class _Rule:
    role: str
    all: frozenset[str]
    none: frozenset[str]
    score: float


@dataclass(frozen=True)
class _Rules:
    prefixes: tuple[re.Pattern[str], ...]
    compounds: dict[str, tuple[str, ...]]
    sides: dict[str, str]  # token -> "Left"/"Right"
    ignore: frozenset[str]
    helper: frozenset[str]
    finger: frozenset[str]
    rules: tuple[_Rule, ...]


@lru_cache(maxsize=1)
def _rules() -> _Rules:
    raw = json.loads(resources.files("retarget_core").joinpath("data/mapping_aliases.json").read_text("utf-8"))
    sides = {tok: side for side, toks in raw["side_tokens"].items() for tok in toks}
    rules = tuple(
        _Rule(r["role"], frozenset(r["all"]), frozenset(r.get("none", ())), float(r["score"])) for r in raw["rules"]
    )
    for r in rules:
        if r.role not in CENTRAL_ROLES + LIMB_ROLES:
            raise ValueError(f"mapping_aliases.json: unknown role {r.role!r}")
    return _Rules(
        prefixes=tuple(re.compile(p, re.IGNORECASE) for p in raw["strip_prefixes"]),
        compounds={k: tuple(v) for k, v in raw["compounds"].items()},
        sides=sides,
        ignore=frozenset(raw["ignore_tokens"]),
        helper=frozenset(raw["helper_tokens"]),
        finger=frozenset(raw["finger_tokens"]),
        rules=rules,
    )


@dataclass(frozen=True)
class NameInfo:
    """What a joint's name says.

    tokens: normalised lower-case tokens without the side tokens.
    side: ``"Left"``, ``"Right"`` or None.
    ignored: an end site, IK, control or helper bone that is never chosen.
    helper: a twist/roll/share bone: never a limb joint, a weaker central joint (Reallusion's neck is a twist bone).
    finger: a finger or toe-digit bone: never a limb joint.
    scores: role (``"Hips"``, ``"Spine"``, ``"Neck"``, ``"Head"``, ``"Shoulder"`` ... ``"ToeBase"``) -> 0..1.
    """

    tokens: tuple[str, ...]
    side: str | None
    ignored: bool
    helper: bool
    finger: bool
    scores: dict[str, float] = field(default_factory=dict)


def name_tokens(name: str) -> list[str]:
    """Lower-case tokens of a joint name: namespace and one known rig prefix removed, split on separators, camel
    case and digits, compounds (``upperarm``, ``toebase``, ``leftarm``) expanded."""
    rules = _rules()
    base = re.split(r"[:|]", name)[-1]
    for prefix in rules.prefixes:
        stripped = prefix.sub("", base, count=1)
        if stripped != base and stripped.strip(" _-."):
            base = stripped
            break
    tokens: list[str] = []
    for word in re.split(r"[^A-Za-z0-9]+", base):
        for tok in _CAMEL.findall(word):
            tokens.extend(_expand(tok.lower(), rules))
    return tokens


def _expand(tok: str, rules: _Rules) -> list[str]:
    for side in ("left", "right"):
        if tok.startswith(side) and len(tok) > len(side) and tok[len(side) :].isalpha():
            return [side, *_expand(tok[len(side) :], rules)]
    return list(rules.compounds.get(tok, (tok,)))


def analyse_name(name: str) -> NameInfo:
    """Tokens, side, flags and role scores of one joint name (see :class:`NameInfo`)."""
    rules = _rules()
    tokens = name_tokens(name)
    sides = {rules.sides[t] for t in tokens if t in rules.sides}
    side = sides.pop() if len(sides) == 1 else None
    words = tuple(t for t in tokens if t not in rules.sides)
    present = set(words)
    ignored = bool(present & rules.ignore)
    helper = bool(present & rules.helper)
    finger = bool(present & rules.finger)
    scores: dict[str, float] = {}
    if not ignored:
        for rule in rules.rules:
            limb = rule.role in LIMB_ROLES
            if limb and (side is None or helper or finger):
                continue
            if not limb and side is not None:
                continue
            if rule.all <= present and not (rule.none & present):
                score = rule.score * (0.8 if helper else 1.0)
                scores[rule.role] = max(scores.get(rule.role, 0.0), score)
    return NameInfo(words, side, ignored, helper, finger, scores)


# ------------------------------------------------------------------------------------------------ overrides


def load_override(path: str | Path) -> dict[str, str]:
    """Read a JSON override ``{"LeftArm": "my_l_upperarm", ...}`` (a null value leaves that joint unmapped).

    Raises InvalidFileError when the file cannot be read as a JSON object of strings, MappingError naming any
    key that is not a canonical joint. Joint names are checked against a skeleton by :func:`map_joints`.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_OVERRIDE_BYTES:
            raise InvalidFileError(f"a joint-mapping override of {size} bytes is too large", str(path))
        data = json.loads(path.read_text("utf-8"))
    except OSError as exc:
        raise InvalidFileError(f"cannot read the joint-mapping override: {exc.strerror or exc}", str(path)) from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidFileError(f"the joint-mapping override is not valid JSON: {exc}", str(path)) from exc
    if not isinstance(data, dict) or not all(_valid_value(k, v) for k, v in data.items()):
        raise InvalidFileError(
            'the joint-mapping override must be a JSON object like {"LeftArm": "joint name"} '
            '(a twist share: {"LeftForeArmTwist1.share": 0.5})',
            str(path),
        )
    _check_canonical_names(data, str(path))
    return {k: (str(v) if k.endswith(SHARE_SUFFIX) else v) for k, v in data.items()}  # shares as strings (options)


def _valid_value(key: object, value: object) -> bool:
    """A joint name or null, or a number (or numeric string) for a ``.share`` key."""
    if isinstance(key, str) and key.endswith(SHARE_SUFFIX):
        try:
            return not isinstance(value, bool) and abs(float(value)) <= 1.0  # type: ignore[arg-type]
        except (TypeError, ValueError):
            return False
    return isinstance(value, str) or value is None


def _known_key(key: str) -> bool:
    base = key[: -len(SHARE_SUFFIX)] if key.endswith(SHARE_SUFFIX) else None
    return (
        key in CANONICAL_JOINTS
        or key in EXTRA_JOINTS
        or (base is not None and "Twist" in base and base in EXTRA_JOINTS)
    )


def _check_canonical_names(override: dict[str, object], where: str | None = None) -> None:
    unknown = [k for k in override if not _known_key(str(k))]
    if unknown:
        hints = []
        for k in unknown:
            close = difflib.get_close_matches(str(k), CANONICAL_JOINTS + EXTRA_JOINTS, n=1)
            hints.append(f"{k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        prefix = f"{where}: " if where else ""
        raise MappingError(
            f"{prefix}unknown canonical joint(s) in the override: {', '.join(hints)}; "
            f"the canonical joints are {', '.join(CANONICAL_JOINTS)}; extra joints are named like LeftHandIndex1, "
            "LeftHandIndex0 (metacarpal), LeftFootBigToe1, LeftForeArmTwist1 (+ '.share' for its twist share)"
        )


def _resolve_override(skeleton: Skeleton, override: dict[str, str | None] | None) -> dict[str, int | None]:
    if not override:
        return {}
    _check_canonical_names(override)  # type: ignore[arg-type]
    bad = [k for k, v in override.items() if k.endswith(SHARE_SUFFIX) and not _valid_value(k, v)]
    if bad:
        raise MappingError(f"twist share(s) {', '.join(map(repr, bad))} must be numbers between -1 and 1")
    names = {k: v for k, v in override.items() if not k.endswith(SHARE_SUFFIX)}
    missing = [v for v in names.values() if v is not None and skeleton.find(v) is None]
    if missing:
        hints = []
        for v in missing:
            close = difflib.get_close_matches(v, skeleton.names, n=1)
            hints.append(f"{v!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        raise MappingError(f"the override names joint(s) the skeleton does not have: {', '.join(hints)}")
    return {c: (None if v is None else skeleton.index(v)) for c, v in names.items() if c in CANONICAL_JOINTS}


def require_complete(mapping: JointMapping, skeleton_label: str) -> None:
    """Raise MappingError when a required canonical joint is unmapped, naming the joints and how to fix it."""
    missing = mapping.missing(required_only=True)
    if not missing:
        return
    example = json.dumps({m: "<joint name>" for m in missing[:2]})
    raise MappingError(
        f"{skeleton_label}: could not find the required joint(s) {', '.join(missing)}; "
        f"provide a JSON override mapping canonical joints to this skeleton's joint names, e.g. {example}"
    )


# ------------------------------------------------------------------------------------------------ topology


@dataclass(frozen=True)
class _Topology:
    """Where the body's chains branch, from the tree alone (names only mark unusable joints)."""

    hub: int  # where legs and spine separate
    leg_roots: tuple[int, int]
    spine_root: int
    chest: int  # where the arms branch
    arm_roots: tuple[int, int]
    neck_root: int | None


class _Mapper:
    """One mapping run: the skeleton, what its names say, and the result being built."""

    def __init__(self, skeleton: Skeleton, forced: dict[str, int | None]) -> None:
        self.sk = skeleton
        self.n = skeleton.num_joints
        self.forced = forced
        self.info = [analyse_name(name) for name in skeleton.names]
        self.parents = list(skeleton.parents)
        self.children: list[list[int]] = [[] for _ in range(self.n)]
        for j, p in enumerate(self.parents):
            if p >= 0:
                self.children[p].append(j)
        self.depth = [0] * self.n
        for j, p in enumerate(self.parents):
            self.depth[j] = self.depth[p] + 1 if p >= 0 else 0
        self.bone = [float(v) for v in skeleton.rest_translations.norm(dim=-1)]  # length of the bone ending at j
        counts = [0 if (i.ignored or i.helper) else 1 for i in self.info]
        self.height = list(counts)
        self.size = list(counts)
        for j in range(self.n - 1, -1, -1):
            kids = self.children[j]
            if kids:
                self.height[j] += max(self.height[c] for c in kids)
                self.size[j] += sum(self.size[c] for c in kids)
        self._positions: list[list[float]] | None = None
        self.joints: dict[str, int] = {}
        self.conf: dict[str, float] = {}
        self.method: dict[str, str] = {}
        self.warnings: list[str] = []
        self.side_by_position: set[str] = set()  # "arms"/"legs" whose sides came from rest positions
        self.anchor_method: dict[str, str] = {}  # canonical hand/foot/head -> how it was found
        self.contradicted: set[str] = set()  # named anchors the topology disagrees with

    # ---------------------------------------------------------------- small helpers

    def name(self, j: int) -> str:
        return self.sk.names[j]

    def usable(self, j: int) -> bool:
        """Can be a limb joint: not an end site, helper, control or finger bone."""
        i = self.info[j]
        return not (i.ignored or i.helper or i.finger)

    def limb_joint(self, j: int, side: str) -> bool:
        """Can be a joint of the ``side`` limb when names say nothing better: usable, not the other side's, not
        named like a central joint."""
        i = self.info[j]
        return self.usable(j) and i.side in (None, side) and not any(r in i.scores for r in CENTRAL_ROLES)

    def score(self, j: int, role: str, side: str | None = None) -> float:
        i = self.info[j]
        if role in LIMB_ROLES and i.side != side:
            return 0.0
        return i.scores.get(role, 0.0)

    def position_x(self, j: int) -> float:
        if self._positions is None:
            _, pos = self.sk.rest_global()
            self._positions = pos.tolist()
        return float(self._positions[j][0])

    def is_ancestor(self, a: int, j: int) -> bool:
        """True when ``a`` is ``j`` or one of its ancestors."""
        while j >= 0:
            if j == a:
                return True
            j = self.parents[j]
        return False

    def path(self, top: int, bottom: int) -> list[int]:
        """Joints from ``top`` (excluded) down to ``bottom`` (included); empty unless ``top`` is above ``bottom``."""
        out = []
        j = bottom
        while j >= 0 and j != top:
            out.append(j)
            j = self.parents[j]
        return out[::-1] if j == top else []

    def lca(self, joints: list[int]) -> int | None:
        if not joints:
            return None
        common = [joints[0], *self.sk.ancestors(joints[0])]
        for j in joints[1:]:
            chain = {j, *self.sk.ancestors(j)}
            common = [a for a in common if a in chain]
        return common[0] if common else None

    def best(self, candidates: list[int], key: Callable[[int], float]) -> int | None:
        """The candidate with the highest positive key, ties to the shallowest then the first."""
        scored = [(key(j), -self.depth[j], -j, j) for j in candidates if key(j) > 0]
        return max(scored)[3] if scored else None

    def length(self, path: list[int], a: int, b: int) -> float:
        """Bone length along ``path`` from ``path[a]`` to ``path[b]`` (a <= b)."""
        return sum(self.bone[path[k]] for k in range(a + 1, b + 1))

    def assign(self, canonical: str, joint: int, conf: float, method: str) -> None:
        if canonical in self.forced:
            return  # the override decides, in finish()
        self.joints[canonical] = joint
        self.conf[canonical] = float(max(0.0, min(1.0, conf)))
        self.method[canonical] = method

    def warn(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)

    # ---------------------------------------------------------------- topology

    def long_children(self, j: int) -> list[int]:
        return sorted((c for c in self.children[j] if self.height[c] >= _LONG_BRANCH), key=lambda c: -self.size[c])

    def walk_to_branch(self, j: int) -> int | None:
        """Follow single long branches down to the first joint where two or more long branches start."""
        while True:
            longs = self.long_children(j)
            if len(longs) >= 2:
                return j
            if not longs:
                return None
            j = longs[0]

    def topology(self) -> _Topology | None:
        roots = [j for j, p in enumerate(self.parents) if p < 0]
        if not roots:
            return None
        hub = self.walk_to_branch(max(roots, key=lambda r: self.size[r]))
        if hub is None:
            return None
        branches = self.long_children(hub)
        spine_root = branches[0]
        if len(branches) >= 3:
            legs = branches[1:3]
        else:
            leg_hub = self.walk_to_branch(branches[1])
            if leg_hub is None:
                return None
            legs = self.long_children(leg_hub)[:2]
            if len(legs) < 2:
                return None
        chest = self.walk_to_branch(spine_root)
        if chest is None:
            return None
        longs = self.long_children(chest)
        if len(longs) >= 3:
            pairs = [(a, b) for k, a in enumerate(longs) for b in longs[k + 1 :]]
            arms = min(
                pairs,
                key=lambda ab: (
                    abs(self.size[ab[0]] - self.size[ab[1]]) + abs(self.height[ab[0]] - self.height[ab[1]]),
                    -(self.size[ab[0]] + self.size[ab[1]]),
                ),
            )
            rest = [c for c in longs if c not in arms]
            neck_root: int | None = rest[0]
        else:
            arms = (longs[0], longs[1])
            others = [c for c in self.children[chest] if c not in arms and self.height[c] > 0]
            neck_root = max(others, key=lambda c: (self.height[c], self.size[c])) if others else None
        return _Topology(hub, (legs[0], legs[1]), spine_root, chest, (arms[0], arms[1]), neck_root)

    def main_chain(self, start: int) -> list[int]:
        """``start`` and the joints below it, always following the child with the tallest usable subtree."""
        chain = [start]
        j = start
        while True:
            kids = [c for c in self.children[j] if self.height[c] > 0]
            if not kids:
                return chain
            j = max(kids, key=lambda c: (self.height[c], self.size[c], -c))
            chain.append(j)

    def structural_foot(self, leg_root: int) -> int | None:
        chain = [j for j in self.main_chain(leg_root) if self.usable(j)]
        if len(chain) < 3:
            return None
        # thigh + shin are the two longest consecutive bones of a leg
        segs = [self.length(chain, k, k + 1) for k in range(len(chain) - 1)]
        k = max(range(len(segs) - 1), key=lambda i: segs[i] + segs[i + 1])
        return chain[k + 2]

    def structural_hand(self, arm_root: int) -> int | None:
        chain = [j for j in self.main_chain(arm_root) if self.usable(j)]
        if len(chain) < 3:
            return None
        for j in chain[2:]:  # fingers branch at the hand
            if sum(1 for c in self.children[j] if self.height[c] > 0) >= 2:
                return j
        segs = [self.length(chain, k, k + 1) for k in range(len(chain) - 1)]
        first = 1 if len(chain) >= 4 else 0  # a clavicle precedes the upper arm in longer chains
        k = max(range(first, len(segs) - 1), key=lambda i: segs[i] + segs[i + 1])
        return chain[k + 2]

    def structural_head(self, neck_root: int) -> int | None:
        """The end of the neck chain: where it branches (face bones) or its last joint; a last leaf clearly longer
        than the bone before it is taken for a head-top marker and its parent for the head."""
        j = neck_root
        while True:
            kids = [c for c in self.children[j] if self.height[c] > 0]
            if len(kids) != 1:
                break
            j = kids[0]
        if not self.children[j] and j != neck_root and self.bone[j] > 1.2 * self.bone[self.parents[j]]:
            j = self.parents[j]
        while j >= 0 and (self.info[j].ignored or self.info[j].helper) and j != neck_root:
            j = self.parents[j]
        return j if j >= 0 and not self.info[j].ignored else None

    def side_of_chain(self, top: int, bottom: int) -> str | None:
        sides = {self.info[j].side for j in [top, *self.path(top, bottom)] if self.info[j].side}
        return sides.pop() if len(sides) == 1 else None

    def sided_pair(self, roots: tuple[int, int], ends: tuple[int | None, int | None], what: str) -> dict[str, int]:
        """Left/right of two structural chains: from names, else from rest positions (+X is left)."""
        out: dict[str, int] = {}
        named = [self.side_of_chain(r, e) if e is not None else None for r, e in zip(roots, ends, strict=True)]
        if (named[0] is None) != (named[1] is None):  # one chain's names tell its side: the other is the other
            known = named[0] or named[1]
            other = SIDES[1 - SIDES.index(known or "")]
            named = [n or other for n in named]
        if named[0] and named[1] and named[0] != named[1]:
            for side, e in zip(named, ends, strict=True):
                if side is not None and e is not None:
                    out[side] = e
            return out
        valid = [(r, e) for r, e in zip(roots, ends, strict=True) if e is not None]
        if len(valid) < 2:
            return out
        (r0, e0), (r1, e1) = valid
        left_first = self.position_x(e0) >= self.position_x(e1)
        out["Left"], out["Right"] = (e0, e1) if left_first else (e1, e0)
        self.warn(f"the {what} have no side in their names: left/right taken from rest positions (+X is left)")
        self.side_by_position.add(what)
        return out

    # ---------------------------------------------------------------- anchors

    def anchors(self, topo: _Topology | None) -> tuple[dict[str, int], dict[str, int], int | None]:
        """Hands and feet per side and the head: override, else best name, else topology."""
        hands: dict[str, int] = {}
        feet: dict[str, int] = {}
        everyone = list(range(self.n))

        def fits(j: int, role: str) -> float:
            """1 when the topology agrees a joint can play ``role`` (named candidates that fit come first)."""
            if topo is None:
                return 0.0
            if role == "Hand":
                return float(any(self.is_ancestor(r, j) for r in topo.arm_roots))
            if role == "Foot":
                return float(any(self.is_ancestor(r, j) for r in topo.leg_roots))
            limbs = (*topo.arm_roots, *topo.leg_roots)
            return float(self.is_ancestor(topo.chest, j) and not any(self.is_ancestor(r, j) for r in limbs))

        def key(role: str, side: str | None) -> Callable[[int], float]:
            def rank(j: int) -> float:
                sc = self.score(j, role, side)
                return sc + fits(j, role) if sc > 0 else 0.0

            return rank

        for side in SIDES:
            for role, store in (("Hand", hands), ("Foot", feet)):
                canonical = side + role
                forced = self.forced.get(canonical)
                if forced is not None:
                    store[side] = forced
                    self.anchor_method[canonical] = "override"
                    continue
                found = self.best(everyone, key(role, side))
                if found is not None:
                    store[side] = found
                    self.anchor_method[canonical] = "name"
        head: int | None = self.forced.get("Head")
        if head is not None:
            self.anchor_method["Head"] = "override"
        else:
            head = self.best(everyone, key("Head", None))
            if head is not None:
                self.anchor_method["Head"] = "name"
        if topo is not None:
            self.check_anchors(topo, hands, feet, head)
            if len(hands) < 2:
                ends = (self.structural_hand(topo.arm_roots[0]), self.structural_hand(topo.arm_roots[1]))
                for side, j in self.sided_pair(topo.arm_roots, ends, "arms").items():
                    if side not in hands and j not in hands.values():
                        hands[side] = j
                        self.anchor_method[side + "Hand"] = "structure"
            if len(feet) < 2:
                ends = (self.structural_foot(topo.leg_roots[0]), self.structural_foot(topo.leg_roots[1]))
                for side, j in self.sided_pair(topo.leg_roots, ends, "legs").items():
                    if side not in feet and j not in feet.values():
                        feet[side] = j
                        self.anchor_method[side + "Foot"] = "structure"
            if head is None and topo.neck_root is not None:
                head = self.structural_head(topo.neck_root)
                if head is not None:
                    self.anchor_method["Head"] = "structure"
        return hands, feet, head

    def check_anchors(self, topo: _Topology, hands: dict[str, int], feet: dict[str, int], head: int | None) -> None:
        """Named anchors that sit where the topology puts no such limb lose confidence."""
        for side, j in hands.items():
            if not any(self.is_ancestor(r, j) for r in topo.arm_roots):
                self.contradicted.add(side + "Hand")
                self.warn(f"{self.name(j)!r} is named like a hand but is not at the end of an arm chain")
        for side, j in feet.items():
            if not any(self.is_ancestor(r, j) for r in topo.leg_roots):
                self.contradicted.add(side + "Foot")
                self.warn(f"{self.name(j)!r} is named like a foot but is not at the end of a leg chain")
        if head is not None and (
            any(self.is_ancestor(r, head) for r in (*topo.arm_roots, *topo.leg_roots))
            or not self.is_ancestor(topo.chest, head)
        ):
            self.contradicted.add("Head")
            self.warn(f"{self.name(head)!r} is named like the head but is not above the chest")

    # ---------------------------------------------------------------- chains

    def match_chain(self, path: list[int], roles: tuple[str, ...], side: str | None) -> dict[str, int]:
        """Order-preserving best match of roles to path joints by name score (overrides fixed)."""
        prefix = side or ""

        def s(j: int, role: str) -> float:
            canonical = prefix + role
            if canonical in self.forced:
                return _FORCED if self.forced[canonical] == j else 0.0
            if j in self.forced.values():
                return 0.0
            return self.score(j, role, side)

        n, m = len(path), len(roles)
        neg = float("-inf")
        best = [[neg] * (m + 1) for _ in range(n + 1)]
        move: list[list[int]] = [[0] * (m + 1) for _ in range(n + 1)]  # 1 skip joint, 2 skip role, 3 assign
        best[0][0] = 0.0
        for i in range(n + 1):
            for k in range(m + 1):
                if i == 0 and k == 0:
                    continue
                cands = []
                if i > 0 and best[i - 1][k] > neg:
                    cands.append((best[i - 1][k], 1))
                if k > 0 and best[i][k - 1] > neg:
                    cands.append((best[i][k - 1], 2))
                if i > 0 and k > 0 and best[i - 1][k - 1] > neg:
                    sc = s(path[i - 1], roles[k - 1])
                    if sc > 0:
                        cands.append((best[i - 1][k - 1] + sc - 1e-4 * i, 3))  # ties go to shallower joints
                if cands:
                    best[i][k], move[i][k] = max(cands)
        out: dict[str, int] = {}
        i, k = n, m
        while i > 0 or k > 0:
            mv = move[i][k]
            if mv == 3:
                out[roles[k - 1]] = path[i - 1]
                i, k = i - 1, k - 1
            elif mv == 1:
                i -= 1
            else:
                k -= 1
        return out

    def fill_two_bones(
        self, path: list[int], found: dict[str, int], side: str, upper: str, lower: str, end: str
    ) -> set[str]:
        """Fill the upper/lower joints of an arm or leg the names left open: the elbow/knee is where the two
        long bones are most equal. Returns the roles filled."""
        if end not in found or (upper in found and lower in found):
            return set()
        pos = {j: k for k, j in enumerate(path)}
        e = pos[found[end]]
        lo = -1
        for role, j in found.items():
            if role not in (upper, lower, end) and pos.get(j, -1) < e:
                lo = max(lo, pos[j])
        cand = [k for k in range(lo + 1, e) if self.limb_joint(path[k], side)]
        us = [pos[found[upper]]] if upper in found else cand
        ks = [pos[found[lower]]] if lower in found else cand
        pairs = [(u, k) for u in us for k in ks if u < k < e]
        if not pairs:
            return set()

        def cost(uk: tuple[int, int]) -> tuple[float, float]:
            a, b = self.length(path, uk[0], uk[1]), self.length(path, uk[1], e)
            return (abs(a - b) / (a + b) if a + b > 0 else 1.0, -(a + b))

        u, k = min(pairs, key=cost)
        filled = set()
        if upper not in found:
            found[upper] = path[u]
            filled.add(upper)
        if lower not in found:
            found[lower] = path[k]
            filled.add(lower)
        return filled

    def map_limb(self, top: int, anchor: int, side: str, roles: tuple[str, ...], upper: str, lower: str) -> None:
        path = self.path(top, anchor)
        if not path:
            self.warn(f"{self.name(anchor)!r} is not below {self.name(top)!r}: its chain cannot be followed")
            return
        found = self.match_chain(path, roles, side)
        end = roles[-1]
        named = {r for r, j in found.items() if self.score(j, r, side) > 0 and side + r not in self.forced}
        if end not in found:
            found[end] = anchor
        filled = self.fill_two_bones(path, found, side, upper, lower, end)
        if roles[0] not in found and upper in found and side + roles[0] not in self.forced:  # the clavicle
            first = next((j for j in path if self.limb_joint(j, side)), None)
            if first is not None and path.index(first) < path.index(found[upper]):
                found[roles[0]] = first
                filled.add(roles[0])
        complete = all(r in named for r in roles)
        what = "arms" if end == "Hand" else "legs"
        weak = self.anchor_method.get(side + end) == "structure"
        anchor_factor = SIDE_BY_POSITION_FACTOR if weak and what in self.side_by_position else 1.0
        if side + end in self.contradicted:
            anchor_factor *= CONTRADICTION_FACTOR
        for role in roles[:-1]:  # e.g. a clearly named forearm below the hand: the names contradict the tree
            strays = [
                j
                for j in range(found[end] + 1, self.n)
                if self.score(j, role, side) >= 0.9 and self.is_ancestor(found[end], j) and j not in found.values()
            ]
            if strays:
                anchor_factor *= CONTRADICTION_FACTOR
                self.warn(
                    f"{self.name(strays[0])!r} is named like {side}{role} but lies below {side}{end} "
                    f"({self.name(found[end])!r}): the {side.lower()} {'arm' if end == 'Hand' else 'leg'} is uncertain"
                )
                break
        for role, j in found.items():
            canonical = side + role
            if role in named:
                conf = self.score(j, role, side)
                if complete:
                    conf = max(conf, 0.85)
                self.assign(canonical, j, conf * anchor_factor, "name")
            elif role in filled:
                self.assign(
                    canonical, j, (CONF_STRUCTURE_WEAK if weak else CONF_STRUCTURE) * anchor_factor, "structure"
                )
            elif role == end:
                self.assign(canonical, j, CONF_STRUCTURE_WEAK * anchor_factor, "structure")

    def map_toe(self, side: str, foot: int) -> None:
        """The best toe-named joint below the foot, else the foot's main child."""
        canonical = side + "ToeBase"
        by_position = self.anchor_method.get(side + "Foot") == "structure" and "legs" in self.side_by_position
        factor = SIDE_BY_POSITION_FACTOR if by_position else 1.0
        below = [j for j in range(foot + 1, self.n) if self.is_ancestor(foot, j)]
        toe = self.best(below, lambda j: self.score(j, "ToeBase", side))
        if toe is not None:
            self.assign(canonical, toe, self.score(toe, "ToeBase", side) * factor, "name")
            return
        kids = [c for c in self.children[foot] if self.limb_joint(c, side) and self.height[c] > 0]
        if kids:
            toe = max(kids, key=lambda c: (self.height[c], self.size[c], -c))
            self.assign(canonical, toe, CONF_STRUCTURE_WEAK * factor, "structure")

    # ---------------------------------------------------------------- centre

    def map_hips(self, feet: dict[str, int], upper: int | None) -> int | None:
        if self.forced.get("Hips") is not None:
            return self.forced["Hips"]
        if len(feet) == 2 and upper is not None:
            low = self.lca([feet["Left"], feet["Right"], upper])
            if low is not None:
                # deepest first; above the branching joint only a clear name counts (not Rigify's 'root' bone)
                chain = [low, *self.sk.ancestors(low)]
                named = [j for j in chain if self.score(j, "Hips") >= (1e-9 if j == low else 0.9)]
                if named:  # the branching joint itself is sure whatever its name's strength ('root')
                    sc = self.score(named[0], "Hips")
                    self.assign("Hips", named[0], max(sc, 0.85) if named[0] == low else 0.9 * sc, "name")
                    return named[0]
                self.assign("Hips", low, 0.7, "structure")
                return low
        hips = self.best(list(range(self.n)), lambda j: self.score(j, "Hips"))
        if hips is not None:
            self.assign("Hips", hips, self.score(hips, "Hips") * CONTRADICTION_FACTOR, "name")
            self.warn("Hips chosen by name alone: the legs and the chest could not be located to check it")
        return hips

    def map_spine(self, hips: int, chest: int) -> list[int]:
        """Distribute the joints from Hips to the chest onto Spine/Spine1/Spine2; returns the neck-named joints
        trimmed from the top of that chain."""
        chain = [j for j in self.path(hips, chest) if not self.info[j].ignored]
        trimmed: list[int] = []
        while chain and self.score(chain[-1], "Neck") > self.score(chain[-1], "Spine"):
            trimmed.insert(0, chain.pop())
        if not chain:
            self.warn("no joint between Hips and the shoulders: Spine, Spine1 and Spine2 are not mapped")
            return trimmed
        labels: dict[str, int] = {"Spine2": chain[-1]}
        if len(chain) >= 2:
            labels["Spine"] = chain[0]
        if len(chain) >= 3:
            total = self.length(chain, 0, len(chain) - 1)
            mids = range(1, len(chain) - 1)
            if total > 0:
                k = min(mids, key=lambda i: (abs(self.length(chain, 0, i) - total / 2), i))
            else:
                k = len(chain) // 2
            labels["Spine1"] = chain[k]
        if len(chain) == 2:
            self.warn("only 2 spine joints: Spine1 is not mapped")
        elif len(chain) == 1:
            self.warn("only 1 spine joint (mapped to Spine2): Spine and Spine1 are not mapped")
        literal = {"".join(name_tokens(c)): c for c in ("Spine", "Spine1", "Spine2")}
        renamed = False
        for canonical, j in labels.items():
            clash = literal.get("".join(name_tokens(self.name(j))), canonical) != canonical  # 'Spine' -> Spine1
            renamed |= clash
            if self.score(j, "Spine") > 0 and not clash:
                self.assign(canonical, j, 0.9 if len(chain) == 3 else 0.75, "name")
            else:
                self.assign(canonical, j, CONF_STRUCTURE if clash else CONF_STRUCTURE_WEAK, "structure")
        if renamed:
            order = sorted(labels.items(), key=lambda cj: self.depth[cj[1]])
            self.warn(
                "spine joints are assigned by their place between Hips and the shoulders: "
                + ", ".join(f"{self.name(j)!r} -> {c}" for c, j in order)
            )
        return trimmed

    def map_neck(self, chest: int, head: int, trimmed: list[int]) -> None:
        chain = trimmed + [j for j in self.path(chest, head)[:-1] if not self.info[j].ignored]
        if not chain:
            self.warn(f"the head {self.name(head)!r} hangs directly below the chest: Neck is not mapped")
            return
        named = [j for j in chain if self.score(j, "Neck") > 0]
        if named:
            self.assign("Neck", named[0], self.score(named[0], "Neck"), "name")
        else:
            self.assign("Neck", chain[0], CONF_STRUCTURE, "structure")

    # ---------------------------------------------------------------- whole run

    def run(self) -> JointMapping:
        topo = self.topology()
        hands, feet, head = self.anchors(topo)
        chest: int | None = None
        if len(hands) == 2:
            chest = self.lca([hands["Left"], hands["Right"]])
        elif topo is not None:
            chest = topo.chest
        upper = chest if chest is not None else head
        hips = self.map_hips(feet, upper)

        if head is not None:
            method = self.anchor_method.get("Head", "name")
            conf = self.score(head, "Head") if method == "name" else CONF_STRUCTURE_WEAK
            if "Head" in self.contradicted:
                conf *= CONTRADICTION_FACTOR
            self.assign("Head", head, conf, method)
        trimmed: list[int] = []
        if hips is not None and chest is not None and self.is_ancestor(hips, chest) and hips != chest:
            trimmed = self.map_spine(hips, chest)
        elif chest is not None:
            self.warn("the chest is not below Hips: the spine joints are not mapped")
        if chest is not None and head is not None and self.is_ancestor(chest, head) and chest != head:
            self.map_neck(chest, head, trimmed)

        for side in SIDES:
            if side in hands:
                top = next((t for t in (chest, hips) if t is not None and self.is_ancestor(t, hands[side])), -1)
                if top != hands[side]:
                    self.map_limb(top, hands[side], side, ARM_ROLES, "Arm", "ForeArm")
            if side in feet:
                top = hips if hips is not None and self.is_ancestor(hips, feet[side]) else -1
                if top != feet[side]:
                    self.map_limb(top, feet[side], side, LEG_ROLES, "UpLeg", "Leg")
                foot = self.forced.get(side + "Foot", self.joints.get(side + "Foot"))
                if foot is not None and side + "ToeBase" not in self.forced:
                    self.map_toe(side, foot)
        return self.finish()

    def finish(self) -> JointMapping:
        for canonical, j in self.forced.items():
            self.joints.pop(canonical, None)
            self.conf.pop(canonical, None)
            self.method.pop(canonical, None)
            if j is not None:
                self.joints[canonical], self.conf[canonical], self.method[canonical] = j, 1.0, "override"
        self.drop_duplicates()
        self.check_hierarchy()
        for c in CANONICAL_JOINTS:
            if c not in self.joints:
                if c in self.forced:
                    continue
                kind = "required" if c in REQUIRED_JOINTS else "optional"
                self.warn(f"{kind} joint {c} not found")
        ordered = {c: self.joints[c] for c in CANONICAL_JOINTS if c in self.joints}
        return JointMapping(
            joints=ordered,
            confidence={c: round(float(self.conf[c]), 4) for c in ordered},
            method={c: self.method[c] for c in ordered},
            warnings=list(self.warnings),
        )

    def drop(self, canonical: str, why: str) -> None:
        j = self.joints.pop(canonical)
        self.conf.pop(canonical, None)
        self.method.pop(canonical, None)
        self.warn(f"{canonical} ({self.name(j)!r}) dropped: {why}")

    def drop_duplicates(self) -> None:
        users: dict[int, list[str]] = {}
        for c, j in self.joints.items():
            users.setdefault(j, []).append(c)
        for cs in users.values():
            if len(cs) < 2:
                continue
            keep = max(cs, key=lambda c: (self.method[c] == "override", self.conf[c], c in REQUIRED_JOINTS))
            for c in cs:
                if c != keep:
                    self.drop(c, f"the joint is already mapped to {keep}")

    def check_hierarchy(self) -> None:
        """Each canonical joint's joint must lie below the joint of its nearest mapped canonical ancestor."""
        for c in CANONICAL_JOINTS:
            if c not in self.joints:
                continue
            p = CANONICAL_PARENT[c]
            while p is not None and p not in self.joints:
                p = CANONICAL_PARENT[p]
            if p is None:
                continue
            jc, jp = self.joints[c], self.joints[p]
            if jc != jp and self.is_ancestor(jp, jc):
                continue
            problem = f"{c} ({self.name(jc)!r}) is not below {p} ({self.name(jp)!r})"
            loser = p if self.method[c] == "override" and self.method[p] != "override" else c
            if self.method[loser] == "override":
                self.warn(problem + " (kept: both come from the override)")
            elif loser not in REQUIRED_JOINTS:
                self.drop(loser, problem)
            else:
                self.conf[loser] = min(self.conf[loser], HIERARCHY_CAP)
                self.warn(problem + f"; {loser} kept with low confidence")


def _vrm_body(skeleton: Skeleton, vrm: dict[str, str] | None, forced: dict[str, int | None]) -> dict[str, int | None]:
    """Canonical joint -> joint index from the file's VRM humanoid bone map, for those the override leaves."""
    index = {name: j for j, name in enumerate(skeleton.names)}
    return {c: index[n] for c, n in (vrm or {}).items() if c in CANONICAL_JOINTS and c not in forced and n in index}


def map_joints(
    skeleton: Skeleton, override: dict[str, str] | None = None, *, vrm: dict[str, str] | None = None
) -> JointMapping:
    """Map ``skeleton``'s joints to the canonical joints by name and structure (see the module docstring), then
    its fingers, toes and twist bones (:mod:`retarget_core.extras`) into ``mapping.extras``.

    override: canonical or extra joint -> joint name (a None value leaves that joint unmapped); these win with
    method ``"override"`` and confidence 1; ``"<twist joint>.share"`` keys set twist shares. Raises MappingError
    when the override names an unknown joint key or a joint the skeleton does not have. Missing required joints
    do not raise: see ``mapping.missing()`` and :func:`require_complete`. vrm: canonical or extra joint -> joint
    name from the file's VRM humanoid bone map (:mod:`retarget_core.io.vrm`); its canonical joints are held like
    an override's (confidence 1, method ``"vrm"``), below the override's own.
    """
    from retarget_core.extras import map_extras

    forced = _resolve_override(skeleton, override)  # type: ignore[arg-type]
    from_vrm = _vrm_body(skeleton, vrm, forced)
    mapping = _Mapper(skeleton, {**from_vrm, **forced}).run()
    for c in from_vrm:  # the file's own bone map: held like an override, reported as such
        if mapping.method.get(c) == "override":
            mapping.method[c] = "vrm"
    map_extras(skeleton, mapping, override, vrm)  # type: ignore[arg-type]
    return mapping


__all__ = [
    "NameInfo",
    "analyse_name",
    "load_override",
    "map_joints",
    "name_tokens",
    "require_complete",
]
