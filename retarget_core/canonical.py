"""The 22 canonical joints every skeleton is mapped to, the extra joints (fingers, toes, twist bones) mapped
beside them, and the result of a mapping."""

from __future__ import annotations

from dataclasses import dataclass, field

CANONICAL_JOINTS: tuple[str, ...] = (
    "Hips", "Spine", "Spine1", "Spine2", "Neck", "Head",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
    "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
)  # fmt: skip

CANONICAL_PARENT: dict[str, str | None] = {
    "Hips": None, "Spine": "Hips", "Spine1": "Spine", "Spine2": "Spine1", "Neck": "Spine2", "Head": "Neck",
    "LeftShoulder": "Spine2", "LeftArm": "LeftShoulder", "LeftForeArm": "LeftArm", "LeftHand": "LeftForeArm",
    "RightShoulder": "Spine2", "RightArm": "RightShoulder", "RightForeArm": "RightArm", "RightHand": "RightForeArm",
    "LeftUpLeg": "Hips", "LeftLeg": "LeftUpLeg", "LeftFoot": "LeftLeg", "LeftToeBase": "LeftFoot",
    "RightUpLeg": "Hips", "RightLeg": "RightUpLeg", "RightFoot": "RightLeg", "RightToeBase": "RightFoot",
}  # fmt: skip

# Joints without which no retarget is attempted; the others are optional (spine joints, shoulders, toes).
REQUIRED_JOINTS: tuple[str, ...] = (
    "Hips", "Head",
    "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
)  # fmt: skip


# Extra joints: mapped when a rig has them, never required, never used by the refinement stages.
FINGERS: tuple[str, ...] = ("Thumb", "Index", "Middle", "Ring", "Pinky")
TOES: tuple[str, ...] = ("BigToe", "IndexToe", "MiddleToe", "RingToe", "PinkyToe")
FINGER_SEGMENTS: tuple[int, ...] = (0, 1, 2, 3)  # 0 = metacarpal (never for the thumb, whose first joint is 1)
TOE_SEGMENTS: tuple[int, ...] = (1, 2, 3)
TWIST_LIMBS: tuple[str, ...] = ("Arm", "ForeArm", "UpLeg", "Leg")
TWIST_SLOTS: tuple[int, ...] = (1, 2, 3)  # twist bones of one limb segment, from its joint toward its end


def _finger_names(side: str) -> list[str]:
    return [f"{side}Hand{f}{k}" for f in FINGERS for k in FINGER_SEGMENTS if not (f == "Thumb" and k == 0)]


EXTRA_JOINTS: tuple[str, ...] = tuple(
    name
    for side in ("Left", "Right")
    for name in (
        *_finger_names(side),
        *(f"{side}Foot{t}{k}" for t in TOES for k in TOE_SEGMENTS),
        *(f"{side}{limb}Twist{k}" for limb in TWIST_LIMBS for k in TWIST_SLOTS),
    )
)
"""``LeftHandIndex1`` (Mixamo's names; ``LeftHandIndex0`` the metacarpal), ``LeftFootBigToe1``, ``LeftForeArmTwist1``."""


def extra_kind(name: str) -> str:
    """``"finger"``, ``"toe"`` or ``"twist"`` for an extra joint name (ValueError for any other name)."""
    if name not in _EXTRA_SET:
        raise ValueError(f"{name!r} is not an extra joint")
    return "twist" if "Twist" in name else "toe" if "Foot" in name else "finger"


_EXTRA_SET = frozenset(EXTRA_JOINTS)


def mirror(name: str) -> str:
    """The canonical joint on the other side (``LeftArm`` -> ``RightArm``); central joints map to themselves."""
    if name.startswith("Left"):
        return "Right" + name[4:]
    if name.startswith("Right"):
        return "Left" + name[5:]
    return name


@dataclass
class JointMapping:
    """Which skeleton joint plays each canonical role.

    joints: canonical name -> joint index in the skeleton (absent when not found).
    confidence: canonical name -> 0..1, how sure the mapper is.
    method: canonical name -> how it was found: ``"name"``, ``"structure"`` or ``"override"``.
    warnings: human-readable problems (missing optional joints, ambiguities).
    extras: extra joint name (:data:`EXTRA_JOINTS`) -> joint index; empty for a rig without fingers, toes or
        twist bones. extra_confidence / extra_method as for the canonical joints (method also ``"vrm"``: the
        file's VRM humanoid bone map).
    twist_share: twist extra -> share of its limb's twist it takes (see :mod:`retarget_core.extras`).
    """

    joints: dict[str, int]
    confidence: dict[str, float] = field(default_factory=dict)
    method: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    extras: dict[str, int] = field(default_factory=dict)
    extra_confidence: dict[str, float] = field(default_factory=dict)
    extra_method: dict[str, str] = field(default_factory=dict)
    twist_share: dict[str, float] = field(default_factory=dict)

    def missing(self, required_only: bool = True) -> list[str]:
        """Canonical joints that were not found."""
        names = REQUIRED_JOINTS if required_only else CANONICAL_JOINTS
        return [n for n in names if n not in self.joints]

    def report(self, joint_names: list[str]) -> dict[str, object]:
        """A JSON-ready report: per canonical joint the skeleton joint, confidence and method."""
        return {
            "joints": {
                c: {
                    "joint": joint_names[self.joints[c]] if c in self.joints else None,
                    "confidence": round(self.confidence.get(c, 0.0), 3),
                    "method": self.method.get(c),
                }
                for c in CANONICAL_JOINTS
            },
            "missing_required": self.missing(True),
            "missing_optional": [n for n in self.missing(False) if n not in REQUIRED_JOINTS],
            "overall_confidence": round(min((self.confidence.get(c, 0.0) for c in REQUIRED_JOINTS), default=0.0), 3),
            "extras": self.extras_report(joint_names),
            "warnings": list(self.warnings),
        }

    def extras_report(self, joint_names: list[str]) -> dict[str, dict[str, object]]:
        """Per mapped extra joint (in :data:`EXTRA_JOINTS` order): joint, confidence, method, kind, and the twist
        share of twist bones."""
        out: dict[str, dict[str, object]] = {}
        for name in EXTRA_JOINTS:
            if name not in self.extras:
                continue
            row: dict[str, object] = {
                "joint": joint_names[self.extras[name]],
                "confidence": round(self.extra_confidence.get(name, 0.0), 3),
                "method": self.extra_method.get(name),
                "kind": extra_kind(name),
            }
            if name in self.twist_share:
                row["share"] = round(self.twist_share[name], 3)
            out[name] = row
        return out
