"""ESO's inner loop skins only the sentinel rows its energy reads: the same points as skinning every sentinel,
on a rig with more joints than body segments (fingers), where joint and segment numbering differ."""

from __future__ import annotations

import torch

from retarget_core.body_cache import body_assets
from retarget_core.kinematics import forward_kinematics
from retarget_core.mapping import map_joints
from retarget_core.model.energy import body_kit
from retarget_core.model.eso import PairCache, _row_plan, _skin_cached, _skin_sentinels, sentinels
from tests.core.extras_rigs import finger_body


def test_cached_rows_are_the_sentinels_skinned() -> None:
    body = finger_body("male_bulky", "mixamo")
    mapping = map_joints(body.skeleton)
    assets, _ = body_assets(body, mapping)
    kit = body_kit(body, mapping, assets.parts, assets.sdf)
    assert kit.rest_rot.shape[0] > len(kit.parts.joints)  # more joints than segments: the case that matters
    sent = sentinels(kit)
    g = torch.Generator().manual_seed(0)
    frames = 5
    sk = body.skeleton
    local = sk.rest_rotations[None].repeat(frames, 1, 1)
    local = torch.nn.functional.normalize(local + 0.2 * torch.randn(local.shape, generator=g), dim=-1)
    grot, gpos = forward_kinematics(sk.parents, local, sk.rest_translations[None].expand(frames, -1, -1))
    frame = torch.randint(0, frames, (300,), generator=g)
    vertex = torch.randint(0, len(sent.index), (300,), generator=g)
    cache = PairCache(frame, vertex, [])
    rows, seg = _skin_cached(kit, _row_plan(sent, cache, kit.rest_rot.shape[0]), grot, gpos)
    posed, seg_all = _skin_sentinels(kit, sent, grot, gpos)
    torch.testing.assert_close(rows, posed[frame, vertex], atol=1e-5, rtol=0)
    torch.testing.assert_close(seg, seg_all)
