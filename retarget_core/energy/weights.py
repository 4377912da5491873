"""Weights of the energy (paper 1, equations 1-9) and of encoder-space optimisation, in one place.

Paper 1, appendix B: at training time lambda = 1000 (vertex contact), beta = 100 (interpenetration),
gamma = 0.1 (foot, ramped in by current_epoch / total_epochs), rho = 1000 (joint rotations), omega = 1000
(end effectors); during ESO rho = 10, beta = 1, lambda = 100, Adam (0.5, 0.999, 1e-8) at lr 0.01, N = 30
steps per frame, contacts optimised only when the network output is within 15 cm of the target, and the
contact target blended 0.7 (initial vertex) / 0.3 (contact vertex). The root-velocity term of E_weak has weight 1.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, Field


class EnergyWeights(BaseModel):
    """Multipliers of the energy terms: E = contact*E_j2j + interpenetration*E_int + foot*E_foot
    + rotation*E_rot + root*E_root + end_effector*E_ee (E_weak = rotation*E_rot + root*E_root)."""

    contact: float = Field(1000.0, ge=0, description="lambda, vertex contact E_j2j")
    interpenetration: float = Field(100.0, ge=0, description="beta, interpenetration E_int")
    foot: float = Field(0.1, ge=0, description="gamma, foot contact E_foot")
    rotation: float = Field(1000.0, ge=0, description="rho, joint rotations in E_weak")
    root: float = Field(1.0, ge=0, description="root velocity in E_weak")
    end_effector: float = Field(1000.0, ge=0, description="omega, end-effector velocities E_ee")


class ESOSettings(BaseModel):
    """Encoder-space optimisation (paper 1, section 3.3 and appendix B)."""

    weights: EnergyWeights = Field(default_factory=lambda: EnergyWeights(contact=100.0, interpenetration=1.0, rotation=10.0))
    iterations: int = Field(30, ge=0)
    learning_rate: float = Field(0.01, gt=0)
    adam_betas: tuple[float, float] = (0.5, 0.999)
    adam_eps: float = 1e-8
    contact_gate_m: float = Field(0.15, gt=0, description="optimise a contact only when already this close (at 1.80 m)")
    contact_target_initial_share: float = Field(0.7, ge=0, le=1, description="share of the initial vertex position in the contact target")


class TrainingSettings(BaseModel):
    """Training of the geometry-conditioned network (paper 1, appendix B.1)."""

    weights: EnergyWeights = Field(default_factory=EnergyWeights)
    foot_ramp: bool = Field(True, description="multiply the foot weight by current_epoch / total_epochs")
    learning_rate: float = 1e-4
    adam_betas: tuple[float, float] = (0.5, 0.999)
    epochs: int = 10
    batch_size: int = 256
    clip_frames: int = 60
    dropout: float = 0.1
    lr_decay_per_epoch: float = 0.95
    subsample_vertices: int = 3000


class EnergyConfig(BaseModel):
    """Everything about the energy, as one document (JSON-serialisable)."""

    training: TrainingSettings = Field(default_factory=TrainingSettings)
    eso: ESOSettings = Field(default_factory=ESOSettings)


def load_energy_config(path: str | Path | None = None) -> EnergyConfig:
    """The paper's configuration, or the one in JSON file ``path`` (fields left out keep the paper's values)."""
    if path is None:
        return EnergyConfig()
    return EnergyConfig.model_validate_json(Path(path).read_text())


__all__ = ["ESOSettings", "EnergyConfig", "EnergyWeights", "TrainingSettings", "load_energy_config"]
