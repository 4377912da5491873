"""Parameters of built-in bodies and the named presets. Light (pydantic only): the API imports it."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class BodyParams(BaseModel):
    """Parameters of a MakeHuman body (immutable, hashable).

    gender: 0 female .. 1 male (MakeHuman's gender macro).
    age: in years, 1..90 (mapped to MakeHuman's age macro: 1 y -> 0, 11 y -> 0.1875, 25 y -> 0.5, 90 y -> 1).
    weight, muscle: MakeHuman's macros, 0 min .. 0.5 average .. 1 max.
    height: target standing height in metres (the rest mesh's vertical extent equals it); None keeps the
        natural height of the other macros (MakeHuman's height macro at 0.5, no scaling).
    proportions: MakeHuman's body-proportions macro, 0 uncommon .. 0.5 neutral .. 1 ideal.
    name: the character's name.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = "makehuman"
    gender: float = Field(default=0.5, ge=0.0, le=1.0)
    age: float = Field(default=25.0, ge=1.0, le=90.0)
    weight: float = Field(default=0.5, ge=0.0, le=1.0)
    muscle: float = Field(default=0.5, ge=0.0, le=1.0)
    height: float | None = Field(default=None, ge=0.5, le=2.5)
    proportions: float = Field(default=0.5, ge=0.0, le=1.0)


PRESETS: dict[str, BodyParams] = {
    "male_average": BodyParams(name="male_average", gender=1.0, age=25.0, weight=0.5, muscle=0.5, height=1.7304),
    "male_skinny": BodyParams(name="male_skinny", gender=1.0, age=25.0, weight=0.0, muscle=0.0, height=1.8750),
    "male_muscular": BodyParams(name="male_muscular", gender=1.0, age=25.0, weight=0.5, muscle=1.0, height=1.8750),
    "male_bulky": BodyParams(name="male_bulky", gender=1.0, age=25.0, weight=1.0, muscle=1.0, height=1.7304),
    "female_average": BodyParams(name="female_average", gender=0.0, age=25.0, weight=0.5, muscle=0.5, height=1.5898),
    "female_skinny": BodyParams(name="female_skinny", gender=0.0, age=25.0, weight=0.0, muscle=0.2, height=1.7362),
    "neutral_tall": BodyParams(name="neutral_tall", gender=0.5, age=25.0, weight=0.3, muscle=0.6, height=1.9485),
    "child": BodyParams(name="child", gender=0.5, age=9.0, weight=0.45, muscle=0.4, height=1.32),
}  # fmt: skip
