"""Paper 2's per-limb self-collision resolution model (section 5), for any body of the canonical skeleton.

One model per limb cluster (left arm, right arm, left leg, right leg), trained together. Each has two parts:

- ``f_Phi`` (5-layer MLP, width 64) maps the pose, the limb's own joint rotations and the body's geometry to the
  semantic matrix ``Phi_c (6, d)``, d = 8;
- each row of ``Phi_c`` is normalised (mean 0, variance 1) and multiplied by the limb's row of the collision
  matrix ``M_col,c (6,)`` (eq. 8): the semantic collision matrix ``Phi'_c``;
- ``f_dq`` (linear layers of width 16 with dense connections: ``Phi'_c`` enters every layer) maps ``Phi'_c`` to one
  residual quaternion per limb joint; the limb's new local rotation is ``q_j * normalize(identity + dq_j)``.

Identity at zero collision by construction (a choice): ``dq = g(Phi') - g(0)``, so a limb whose row of
``M_col`` is zero is returned exactly as given (paper 2 learns it through its identity loss, which we still
compute and which is then zero).

Inputs (all per canonical joint, body-independent, lengths over the shoulder height as paper 2 normalises):
- pose: every joint's position relative to the hips and its skinning rotation (posed world * rest world^-1,
  6D), both in the hips' heading frame; the limb's joints' local rotations (6D): ``q`` and ``q_c`` of the paper;
- body: every joint's rest offset from its parent (``s``) and every segment's rest bounding-box extent (``b``;
  random segment padding grows it by twice the padding, as paper 2 pads the box).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import roma
import torch
from torch import Tensor, nn

from retarget_core.body_parts import CLUSTER_OF, CLUSTERS, BodyParts
from retarget_core.canonical import CANONICAL_JOINTS, JointMapping
from retarget_core.character import Character
from retarget_core.model.collision_geometry import LIMB_ROWS, LIMBS

N_CANON = len(CANONICAL_JOINTS)
LIMB_JOINTS: dict[str, tuple[str, ...]] = {c: tuple(n for n in CANONICAL_JOINTS if CLUSTER_OF[n] == c) for c in LIMBS}
"""Joints each limb model turns (paper 2: the joints of its segment cluster)."""
DEPTH_SCALE = 50.0
"""Collision depths enter the model in shoulder heights times this (about cm at 1.80 m): values of order 1."""


@dataclass(frozen=True)
class CollisionNetConfig:
    """Sizes (paper 2, section 7.1): f_Phi 5 layers of 64, d = 8, f_dq layers of 16 with dense connections."""

    phi_width: int = 64
    phi_layers: int = 5
    d: int = 8
    dq_width: int = 16
    dq_layers: int = 3


def pose_feature_dim(limb: str) -> int:
    """Per-frame input size of ``limb``'s ``f_Phi``: positions + skinning rotations of every joint, the limb's
    local rotations, rest offsets and box extents."""
    return N_CANON * 3 + N_CANON * 6 + len(LIMB_JOINTS[limb]) * 6 + N_CANON * 3 + N_CANON * 3


class DenseResidual(nn.Module):
    """``f_dq``: ``Phi' (B, 6 d)`` -> ``dq (B, K, 4)``; every layer sees ``Phi'`` and all earlier layers."""

    def __init__(self, in_dim: int, width: int, layers: int, joints: int) -> None:
        super().__init__()
        self.joints = joints
        self.hidden = nn.ModuleList(nn.Linear(in_dim + k * width, width) for k in range(layers))
        self.out = nn.Linear(in_dim + layers * width, joints * 4)
        with torch.no_grad():
            self.out.weight.mul_(0.01)
            self.out.bias.zero_()

    def forward(self, x: Tensor) -> Tensor:
        feats = [x]
        for layer in self.hidden:
            feats.append(torch.relu(layer(torch.cat(feats, dim=-1))))
        return self.out(torch.cat(feats, dim=-1)).view(x.shape[0], self.joints, 4)


class LimbResolver(nn.Module):
    """``F_res^c`` of one limb: features ``(B, D)`` and ``M_col,c (B, 6)`` -> ``dq (B, K, 4)``."""

    def __init__(self, in_dim: int, joints: int, cfg: CollisionNetConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = in_dim
        for _ in range(cfg.phi_layers - 1):
            layers += [nn.Linear(width, cfg.phi_width), nn.ReLU()]
            width = cfg.phi_width
        layers.append(nn.Linear(width, len(CLUSTERS) * cfg.d))
        self.phi = nn.Sequential(*layers)
        self.d = cfg.d
        self.dq = DenseResidual(len(CLUSTERS) * cfg.d, cfg.dq_width, cfg.dq_layers, joints)
        self.mean: Tensor
        self.std: Tensor
        self.register_buffer("mean", torch.zeros(in_dim))  # feature normalisation (fit_normalisation)
        self.register_buffer("std", torch.ones(in_dim))

    def semantic(self, feats: Tensor) -> Tensor:
        """The row-normalised semantic matrix ``Phi_c (B, 6, d)``."""
        phi = self.phi((feats - self.mean) / self.std).view(feats.shape[0], len(CLUSTERS), self.d)
        return (phi - phi.mean(-1, keepdim=True)) / (phi.var(-1, unbiased=False, keepdim=True) + 1e-5).sqrt()

    def residual(self, phi: Tensor, m_row: Tensor) -> Tensor:
        """``dq (B, K, 4)`` of ``Phi_c`` and the collision row ``(B, 6)`` (shoulder heights); 0 where the row is 0."""
        sem = (phi * (m_row * DEPTH_SCALE)[..., None]).flatten(1)
        return self.dq(sem) - self.dq(torch.zeros_like(sem))

    def forward(self, feats: Tensor, m_row: Tensor) -> Tensor:
        return self.residual(self.semantic(feats), m_row)


class CollisionNet(nn.Module):
    """The four :class:`LimbResolver` models, keyed by limb cluster name."""

    def __init__(self, cfg: CollisionNetConfig | None = None) -> None:
        super().__init__()
        self.config = cfg or CollisionNetConfig()
        self.limbs = nn.ModuleDict({c: LimbResolver(pose_feature_dim(c), len(LIMB_JOINTS[c]), self.config) for c in LIMBS})


@dataclass
class BodyRig:
    """Per-body inputs of the model. canon: ``(22,)`` skeleton joint of each canonical joint (-1 missing);
    canon_seg: ``(22,)`` its segment in ``parts`` (-1 missing); limb_joints: per limb, skeleton joints ``(K,)``
    (-1 missing); shoulder: shoulder height (m); offsets: ``(22, 3)`` rest offsets from the parent joint and
    extents: ``(22, 3)`` segment box extents (shoulder heights)."""

    canon: Tensor
    canon_seg: Tensor
    limb_joints: dict[str, Tensor]
    shoulder: float
    offsets: Tensor
    extents: Tensor


def body_rig(character: Character, mapping: JointMapping, parts: BodyParts) -> BodyRig:
    """The :class:`BodyRig` of a body."""
    sk = character.skeleton
    _, rest_pos = sk.rest_global()
    canon = torch.tensor([mapping.joints.get(c, -1) for c in CANONICAL_JOINTS], dtype=torch.long)
    canon_seg = torch.tensor([parts.find(c) if parts.find(c) is not None else -1 for c in CANONICAL_JOINTS], dtype=torch.long)
    floor = float(character.vertices[:, 1].min())
    arms = [mapping.joints[n] for n in ("LeftArm", "RightArm") if n in mapping.joints]
    shoulder = float(rest_pos[arms, 1].mean()) - floor if arms else 0.8 * character.height
    offsets = torch.zeros(N_CANON, 3)
    extents = torch.zeros(N_CANON, 3)
    verts = character.vertices.float()
    for k, c in enumerate(CANONICAL_JOINTS):
        j = mapping.joints.get(c)
        if j is None:
            continue
        p = sk.parents[j]
        offsets[k] = (rest_pos[j] - rest_pos[p]) if p >= 0 else rest_pos[j] - torch.tensor([0.0, floor, 0.0])
        s = parts.find(c)
        if s is not None:
            v = verts[parts.vertex_part == s]
            if len(v):
                extents[k] = v.max(0).values - v.min(0).values
    limb_joints = {c: torch.tensor([mapping.joints.get(n, -1) for n in LIMB_JOINTS[c]], dtype=torch.long) for c in LIMBS}
    return BodyRig(canon, canon_seg, limb_joints, shoulder, offsets / shoulder, extents / shoulder)


def _six(m: Tensor) -> Tensor:
    """6D form ``(..., 6)`` of rotation matrices ``(..., 3, 3)`` (first two columns)."""
    return m[..., :2].transpose(-1, -2).reshape(*m.shape[:-2], 6)


def pose_features(rig: BodyRig, local_rot: Tensor, seg_mats: Tensor, gpos: Tensor, pad: Tensor | None = None) -> dict[str, Tensor]:
    """Per limb, ``f_Phi``'s input ``(B, D)`` from local rotation matrices ``(B, J, 3, 3)``, segment transforms
    ``(B, S, 3, 4)`` and joint positions ``(B, J, 3)``; ``pad (B, S)`` grows the box extents (m)."""
    b_n = local_rot.shape[0]
    have = rig.canon >= 0
    seg_rot = seg_mats[..., :3]  # (B, S, 3, 3)
    hips = int(rig.canon_seg[0])
    fwd = seg_rot[:, hips, :, 2]  # rest faces +Z
    yaw = torch.atan2(fwd[:, 0], fwd[:, 2])
    zero = torch.zeros_like(yaw)
    heading_t = roma.rotvec_to_rotmat(torch.stack([zero, -yaw, zero], dim=-1))  # (B, 3, 3): world -> heading frame
    pos = torch.zeros(b_n, N_CANON, 3, dtype=local_rot.dtype)
    rots = torch.zeros(b_n, N_CANON, 6, dtype=local_rot.dtype)
    idx = rig.canon.clamp_min(0)
    root = gpos[:, int(rig.canon[0])]
    p = torch.einsum("bij,bkj->bki", heading_t, gpos.index_select(1, idx) - root[:, None]) / rig.shoulder
    seg = rig.canon_seg.clamp_min(0)
    r = heading_t[:, None] @ seg_rot.index_select(1, seg)
    pos = torch.where(have[None, :, None], p, pos)
    rots = torch.where((rig.canon_seg >= 0)[None, :, None], _six(r), rots)
    extents = rig.extents.expand(b_n, -1, -1)
    if pad is not None:
        seg_pad = torch.where(rig.canon_seg >= 0, pad.index_select(1, seg), torch.zeros_like(pad[:, :1]))
        extents = extents + 2.0 * seg_pad[..., None] / rig.shoulder
    common = [pos.flatten(1), rots.flatten(1), rig.offsets.expand(b_n, -1, -1).flatten(1), extents.flatten(1)]
    out = {}
    for c in LIMBS:
        lj = rig.limb_joints[c]
        lr = _six(local_rot.index_select(1, lj.clamp_min(0))) * (lj >= 0)[None, :, None]
        out[c] = torch.cat([common[0], common[1], lr.flatten(1), common[2], common[3]], dim=-1)
    return out


def apply_residuals(rig: BodyRig, local_rot: Tensor, dq: dict[str, Tensor]) -> Tensor:
    """Local rotation matrices ``(B, J, 3, 3)`` with each limb joint turned by its residual quaternion
    ``normalize(identity + dq)`` (xyzw, ``dq[limb] (B, K, 4)``) in its local frame."""
    out = local_rot
    for c, d in dq.items():
        lj = rig.limb_joints[c]
        ok = torch.nonzero(lj >= 0).flatten()
        if len(ok) == 0:
            continue
        joints = lj.index_select(0, ok)
        q = d.index_select(1, ok) + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=d.dtype)
        res = roma.unitquat_to_rotmat(q / q.norm(dim=-1, keepdim=True))
        out = out.index_copy(1, joints, out.index_select(1, joints) @ res)
    return out


def run_model(model: CollisionNet, feats: dict[str, Tensor], m_col: Tensor, shoulder: float) -> dict[str, Tensor]:
    """Per limb ``dq (B, K, 4)`` from its features and its row of ``M_col (B, 6, 6)`` (m at the body's scale)."""
    return {c: model.limbs[c](feats[c], m_col[:, r] / shoulder) for c, r in zip(LIMBS, LIMB_ROWS, strict=True)}


def save_collision_net(model: CollisionNet, path: Path, meta: dict[str, Any]) -> None:
    """Weights and meta (config, training summary) in one small file, stored in half precision."""
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.half() if v.is_floating_point() else v for k, v in model.state_dict().items()}
    torch.save({"config": asdict(model.config), "state": state, "meta": meta}, path)


def load_collision_net(path: str | Path, device: str = "cpu") -> tuple[CollisionNet, dict[str, Any]]:
    """The model saved by :func:`save_collision_net` (float32, eval mode) and its meta."""
    blob = torch.load(path, map_location="cpu", weights_only=False)
    model = CollisionNet(CollisionNetConfig(**blob["config"]))
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in blob["state"].items()})
    return model.to(device).eval(), dict(blob.get("meta", {}))


__all__ = [
    "DEPTH_SCALE",
    "LIMB_JOINTS",
    "BodyRig",
    "CollisionNet",
    "CollisionNetConfig",
    "DenseResidual",
    "LimbResolver",
    "apply_residuals",
    "body_rig",
    "load_collision_net",
    "pose_feature_dim",
    "pose_features",
    "run_model",
    "save_collision_net",
]
