"""``inspect_file``: what a file holds, as a JSON-ready dict (used by the CLI and by upload validation)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from retarget_core.loading import load_character, load_motion


def inspect_file(path: str | Path, kind: Literal["character", "motion"]) -> dict[str, Any]:
    """Read ``path`` as a character or a motion and describe it; raises RetargetError subclasses on bad files."""
    if kind == "motion":
        lm = load_motion(path)
        m = lm.motion
        return {
            "kind": "motion",
            "format": lm.format,
            "name": m.name,
            "joints": m.skeleton.names,
            "joint_count": m.skeleton.num_joints,
            "frames": m.num_frames,
            "fps": m.fps,
            "duration_s": round(m.duration, 4),
            "clips": lm.clips,
            "has_mesh": lm.source_character is not None,
            "meshes": [m.as_dict() for m in lm.source_character.character.meshes] if lm.source_character else [],
            "mapping": lm.mapping.report(m.skeleton.names),
            "normalization": lm.normalization.as_dict(),
            "warnings": lm.notes + lm.mapping.warnings,
        }
    lc = load_character(path)
    c = lc.character
    return {
        "kind": "character",
        "format": lc.format,
        "name": c.name,
        "joints": c.skeleton.names,
        "joint_count": c.skeleton.num_joints,
        "vertices": c.num_vertices,
        "triangles": int(c.faces.shape[0]),
        "meshes": [m.as_dict() for m in c.meshes],  # roles per mesh (docs/meshes.md)
        "height_m": round(c.height, 4),
        "mapping": lc.mapping.report(c.skeleton.names),
        "normalization": lc.normalization.as_dict(),
        "warnings": lc.notes + lc.mapping.warnings,
    }
