"""Options of one retarget job. Light (pydantic only) so the API can validate requests without torch."""

from __future__ import annotations

from pydantic import BaseModel, Field, model_validator


class StageSwitches(BaseModel):
    """Which pipeline stages run. Stages that do not exist yet in this version are ignored with a note."""

    contacts: bool = True
    recurrent: bool = True
    eso: bool = True
    collisions: bool = True
    foot_lock: bool = True


class RetargetOptions(BaseModel):
    """What a user may choose for one motion x character job."""

    fps: float | None = Field(default=None, ge=1, le=240, description="Output frame rate; default: the source's")
    frame_start: int = Field(default=0, ge=0, le=10_000_000, description="First source frame (inclusive)")
    frame_end: int | None = Field(default=None, ge=1, le=10_000_000,
                                  description="Last source frame (exclusive); default: the end")
    clip: str | None = Field(default=None, max_length=300,
                             description="Animation name or index when the motion file has several")
    in_place: bool = Field(default=False, description="Remove horizontal root motion")
    eso_iterations: int = Field(default=30, ge=0, le=1000, description="Encoder-space optimisation steps per window")
    stages: StageSwitches = Field(default_factory=StageSwitches)
    joint_map_override: dict[str, str] | None = Field(
        default=None, description="Canonical joint name -> joint name in the motion's skeleton"
    )
    target_joint_map_override: dict[str, str] | None = Field(
        default=None, description="Canonical joint name -> joint name in the target's skeleton"
    )

    @model_validator(mode="after")
    def _frame_range(self) -> RetargetOptions:
        if self.frame_end is not None and self.frame_end <= self.frame_start:
            raise ValueError("frame_end must be greater than frame_start")
        return self
