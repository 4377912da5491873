"""``/v1/motions``: clips (BVH, glTF/GLB, FBX)."""

from __future__ import annotations

from api.routes.assets import make_router

router = make_router("motion")
