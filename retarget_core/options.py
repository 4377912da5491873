"""Options of one retarget job. Light (pydantic only) so the API can validate requests without torch."""

from __future__ import annotations

from pydantic import BaseModel, Field, create_model, model_validator

from retarget_core.stages import STAGES


class _StageSwitchesBase(BaseModel):
    def enabled(self, name: str) -> bool:
        """Whether stage ``name`` is switched on."""
        return bool(getattr(self, name))


StageSwitches = create_model(  # one bool per stage of :data:`retarget_core.stages.STAGES`
    "StageSwitches",
    __base__=_StageSwitchesBase,
    __doc__="Which pipeline stages run (stages not available in this version are skipped with a note).",
    **{s.name: (bool, Field(default=s.default, description=s.description)) for s in STAGES},  # type: ignore[call-overload]
)


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
    device: str = Field(default="cpu", pattern=r"^(cpu|cuda(:\d+)?|auto)$", description="Torch device: cpu, cuda, cuda:N or auto")
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
