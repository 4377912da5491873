"""Named built-in bodies and a sampler of random plausible bodies (the training bank).

The adult presets are the parameters of the shared characters ``mh_*.glb`` (found by fitting the generator to
them: it reproduces their vertices and joints to float precision), so a preset and the shared file of the same
name are interchangeable.
"""

from __future__ import annotations

import numpy as np

from retarget_core.bodies.makehuman import make_body
from retarget_core.bodies.params import PRESETS, BodyParams
from retarget_core.character import Character


def list_presets() -> list[str]:
    """The names of the built-in bodies, sorted."""
    return sorted(PRESETS)


def preset_params(name: str) -> BodyParams:
    """The parameters of preset ``name`` (ValueError naming the valid presets if unknown)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown body preset {name!r}; valid presets: {', '.join(list_presets())}") from None


def load_preset(name: str) -> Character:
    """The built-in body ``name`` (cached in-process by :func:`make_body`; each call gets its own copy)."""
    return make_body(preset_params(name))


# Median standing height in metres by age (years) for boys and girls, adults after 18: rounded values of the
# CDC 2000 growth charts (2-20 y), flat in adulthood with a slight decline in old age.
_HEIGHT_AGES = np.array([1.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 40.0, 90.0])
_HEIGHT_MALE = np.array([0.76, 0.87, 1.03, 1.16, 1.28, 1.39, 1.50, 1.64, 1.74, 1.76, 1.76, 1.72])
_HEIGHT_FEMALE = np.array([0.74, 0.86, 1.02, 1.15, 1.27, 1.38, 1.51, 1.60, 1.62, 1.63, 1.63, 1.59])

CHILD_FRACTION = 0.1  # share of children (6-17 years) in the sampled bank
HEIGHT_RELATIVE_SD = 0.04  # about 7 cm for adults


def typical_height(gender: float, age: float) -> float:
    """Median standing height in metres for ``gender`` (0 female .. 1 male, interpolated) and ``age`` years."""
    male = float(np.interp(age, _HEIGHT_AGES, _HEIGHT_MALE))
    female = float(np.interp(age, _HEIGHT_AGES, _HEIGHT_FEMALE))
    return female + gender * (male - female)


def sample_body_params(rng: np.random.Generator, name: str = "sampled") -> BodyParams:
    """A random plausible body: mostly adults (18-70 years; children 6-17 with probability ``CHILD_FRACTION``),
    gender from Beta(0.7, 0.7) (mostly clearly female or male, some in between), weight and muscle from
    Beta(2.5, 2.5), proportions from Beta(3, 3), height the median for gender and age times
    ``1 + N(0, HEIGHT_RELATIVE_SD)`` clipped to 2.5 standard deviations. Deterministic for a given ``rng`` state."""
    child = rng.random() < CHILD_FRACTION
    age = float(rng.uniform(6.0, 17.0) if child else rng.uniform(18.0, 70.0))
    gender = float(rng.beta(0.7, 0.7))
    weight = float(rng.beta(2.5, 2.5))
    muscle = float(rng.beta(2.5, 2.5))
    proportions = float(rng.beta(3.0, 3.0))
    z = float(np.clip(rng.normal(), -2.5, 2.5))
    height = typical_height(gender, age) * (1.0 + HEIGHT_RELATIVE_SD * z)
    return BodyParams(
        name=name,
        gender=gender,
        age=age,
        weight=weight,
        muscle=muscle,
        proportions=proportions,
        height=round(height, 4),
    )


__all__ = ["PRESETS", "list_presets", "load_preset", "preset_params", "sample_body_params", "typical_height"]
