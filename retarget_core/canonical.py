"""The 22 canonical joints every skeleton is mapped to, and the result of a mapping."""

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
    """

    joints: dict[str, int]
    confidence: dict[str, float] = field(default_factory=dict)
    method: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

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
            "warnings": list(self.warnings),
        }
