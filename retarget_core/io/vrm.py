"""The VRM humanoid bone map of a glTF/VRM file (``extensions.VRM`` 0.x or ``extensions.VRMC_vrm`` 1.0), as
extra-joint names (``LeftHandIndex1``) -> joint names.

VRM 1.0 names the thumb ``Metacarpal, Proximal, Distal`` and VRM 0.x ``Proximal, Intermediate, Distal``; both are
the thumb's three joints from the hand, ``Thumb1..3`` here. The other fingers' ``Proximal, Intermediate, Distal``
are segments 1..3 (VRM has no metacarpal for them). VRM has no toe digits or twist bones (its ``leftToes`` is the
canonical ToeBase). Canonical bones are returned by :func:`humanoid_canonical` for a cross-check only.
"""

from __future__ import annotations

import re
from typing import Any

_FINGER = {"Thumb": "Thumb", "Index": "Index", "Middle": "Middle", "Ring": "Ring", "Little": "Pinky"}
_SEGMENT_V1 = {"Metacarpal": 1, "Proximal": 2, "Distal": 3}  # the thumb in VRM 1.0
_SEGMENT = {"Proximal": 1, "Intermediate": 2, "Distal": 3}
_CANONICAL = {
    "hips": "Hips", "spine": "Spine", "neck": "Neck", "head": "Head",
    "Shoulder": "Shoulder", "UpperArm": "Arm", "LowerArm": "ForeArm", "Hand": "Hand",
    "UpperLeg": "UpLeg", "LowerLeg": "Leg", "Foot": "Foot", "Toes": "ToeBase",
}  # fmt: skip
_BONE = re.compile(r"(left|right)(Thumb|Index|Middle|Ring|Little)(Metacarpal|Proximal|Intermediate|Distal)")


def humanoid_bones(doc: dict[str, Any]) -> tuple[dict[str, int], int]:
    """VRM bone name -> node index, and the VRM major version (0 or 1; ``({}, 0)`` without a VRM extension).
    Malformed entries are skipped: the map is a hint, never a reason to reject a file."""
    ext = doc.get("extensions") if isinstance(doc, dict) else None
    if not isinstance(ext, dict):
        return {}, 0
    v1 = ext.get("VRMC_vrm")
    if isinstance(v1, dict) and isinstance(v1.get("humanoid"), dict):
        raw = v1["humanoid"].get("humanBones")
        if isinstance(raw, dict):
            return {
                str(b): v["node"] for b, v in raw.items() if isinstance(v, dict) and isinstance(v.get("node"), int)
            }, 1
    v0 = ext.get("VRM")
    if isinstance(v0, dict) and isinstance(v0.get("humanoid"), dict):
        raw = v0["humanoid"].get("humanBones")
        if isinstance(raw, list):
            return {
                str(b["bone"]): b["node"]
                for b in raw
                if isinstance(b, dict) and isinstance(b.get("bone"), str) and isinstance(b.get("node"), int)
            }, 0
    return {}, 0


def humanoid_extras(doc: dict[str, Any], node_joint: dict[int, str]) -> dict[str, str]:
    """Extra joint -> joint name from the file's VRM finger bones (``node_joint``: node index -> joint name)."""
    bones, version = humanoid_bones(doc)
    out: dict[str, str] = {}
    for bone, node in bones.items():
        match = _BONE.fullmatch(bone)
        if match is None or node not in node_joint:
            continue
        side, finger, part = match.groups()
        table = _SEGMENT_V1 if finger == "Thumb" and version == 1 else _SEGMENT
        if part not in table:
            continue
        out[f"{side.capitalize()}Hand{_FINGER[finger]}{table[part]}"] = node_joint[node]
    return out


def humanoid_canonical(doc: dict[str, Any], node_joint: dict[int, str]) -> dict[str, str]:
    """Canonical joint -> joint name for the VRM body bones that have one obvious canonical name."""
    bones, _ = humanoid_bones(doc)
    out: dict[str, str] = {}
    for bone, node in bones.items():
        if node not in node_joint:
            continue
        side = "Left" if bone.startswith("left") else "Right" if bone.startswith("right") else ""
        key = bone[len(side) :] if side else bone
        if key in _CANONICAL and (side or key.islower()):
            out[side + _CANONICAL[key]] = node_joint[node]
    return out


__all__ = ["humanoid_bones", "humanoid_canonical", "humanoid_extras"]
