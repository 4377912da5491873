"""Generated hostile uploads (no stored blobs): malformed, over-limit and out-of-range BVH and glTF files.

``cases()`` yields (name, kind, file name, bytes, must_fail, expect): ``must_fail`` cases must be refused with a
4xx naming the problem, and the message must contain ``expect`` (case-insensitive) when it is given, so a case
is refused by the check it targets (the BVH cases use a valid human skeleton, so none is refused merely for not
being one); the seeded byte mutations of a valid file may also be accepted (they must never be a 5xx).
"""

from __future__ import annotations

import base64
import json
import random
import struct
from collections.abc import Iterator

Case = tuple[str, str, str, bytes, bool, str | None]

# A CMU-like human skeleton (name, parent, OFFSET in cm): the mapper finds every joint it needs, so a hostile
# field in it is refused by the check that targets that field, not as "not a human skeleton".
HUMAN: list[tuple[str, str | None, tuple[float, float, float]]] = [
    ("Hips", None, (0, 0, 0)), ("LowerBack", "Hips", (0, 2, 0)), ("Spine", "LowerBack", (0, 10, 0)),
    ("Spine1", "Spine", (0, 10, 0)), ("Neck", "Spine1", (0, 15, 0)), ("Head", "Neck", (0, 8, 0)),
    ("LeftShoulder", "Spine1", (3, 12, 0)), ("LeftArm", "LeftShoulder", (15, 0, 0)),
    ("LeftForeArm", "LeftArm", (28, 0, 0)), ("LeftHand", "LeftForeArm", (25, 0, 0)),
    ("RightShoulder", "Spine1", (-3, 12, 0)), ("RightArm", "RightShoulder", (-15, 0, 0)),
    ("RightForeArm", "RightArm", (-28, 0, 0)), ("RightHand", "RightForeArm", (-25, 0, 0)),
    ("LeftUpLeg", "Hips", (9, -5, 0)), ("LeftLeg", "LeftUpLeg", (0, -42, 0)), ("LeftFoot", "LeftLeg", (0, -40, 0)),
    ("LeftToeBase", "LeftFoot", (0, -5, 12)), ("RightUpLeg", "Hips", (-9, -5, 0)),
    ("RightLeg", "RightUpLeg", (0, -42, 0)), ("RightFoot", "RightLeg", (0, -40, 0)),
    ("RightToeBase", "RightFoot", (0, -5, 12)),
]
ROOT_CHANNELS = "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"


def bvh(frames: int = 4, frame_time: str = "0.033333", offsets: dict[str, str] | None = None,
        rows: list[str] | None = None, declared: str | None = None, channels: str = "Zrotation Xrotation Yrotation",
        extra_joints: int = 0, zero: bool = False, root_row: str | None = None) -> bytes:
    """A BVH of the human skeleton above (plus ``extra_joints`` leaf joints on the head): ``offsets`` replaces
    the OFFSET of named joints, ``zero`` makes every OFFSET (and End Site) 0, ``root_row`` the root's six
    values in every frame, ``rows`` the whole MOTION body."""
    offsets = offsets or {}
    children: dict[str | None, list[str]] = {}
    for name, parent, _ in HUMAN:
        children.setdefault(parent, []).append(name)
    chain = [f"Extra{i}" for i in range(extra_joints)]
    children.setdefault("Head", []).extend(chain)
    offset_of = {name: off for name, _, off in HUMAN} | {name: (0, 1, 0) for name in chain}
    lines = ["HIERARCHY"]

    def emit(name: str, depth: int) -> None:
        pad = "  " * depth
        off = "0 0 0" if zero else offsets.get(name, " ".join(f"{v:g}" for v in offset_of[name]))
        lines.extend([f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {name}", f"{pad}{{", f"{pad}  OFFSET {off}",
                      f"{pad}  {ROOT_CHANNELS if depth == 0 else 'CHANNELS 3 ' + channels}"])
        kids = children.get(name, [])
        for kid in kids:
            emit(kid, depth + 1)
        if not kids:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {'0 0 0' if zero else '0 3 0'}",
                          f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit("Hips", 0)
    per = 6 + 3 * (len(HUMAN) - 1 + extra_joints)
    rest = " ".join(["0.0"] * (per - 6))
    body = rows if rows is not None else [f"{root_row or '0 90 0 0 0 0'} {rest}"] * frames
    lines += ["MOTION", f"Frames: {declared if declared is not None else frames}", f"Frame Time: {frame_time}"]
    return ("\n".join(lines + body) + "\n").encode()


def gltf(doc: dict[str, object]) -> bytes:
    return json.dumps({"asset": {"version": "2.0"}, **doc}).encode()


def glb(doc: dict[str, object], binary: bytes = b"") -> bytes:
    js = json.dumps({"asset": {"version": "2.0"}, **doc}).encode()
    js += b" " * (-len(js) % 4)
    out = struct.pack("<II", len(js), 0x4E4F534A) + js
    if binary:
        binary += b"\x00" * (-len(binary) % 4)
        out += struct.pack("<II", len(binary), 0x004E4942) + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(out)) + out


def _bvh_cases() -> Iterator[Case]:
    per = 6 + 3 * (len(HUMAN) - 1)

    def row(value: str, column: int = 5) -> str:
        vals = ["0"] * per
        vals[column] = value
        return " ".join(vals)

    for ft, why in (("0", "positive number"), ("-1", "positive number"), ("1e300", "outside"), ("1e-300", "outside"),
                    ("nan", "positive number"), ("inf", "positive number"), ("abc", "not a number"),
                    ("1e-5", "outside"), ("20", "outside"), ("", "frame time"), ("0x10", "not a number")):
        yield f"bvh frame time {ft!r}", "motion", "ft.bvh", bvh(frame_time=ft), True, why
    for decl, why in (("0", "0 frames"), ("-1", "whole number"), ("99999999999999999999", "limit"),
                      ("1e3", "whole number"), ("12", "declares 12 frames"), ("x", "whole number"),
                      ("3.5", "whole number")):
        yield f"bvh frames {decl!r}", "motion", "fr.bvh", bvh(declared=decl), True, why
    yield "bvh zero offsets", "motion", "zero.bvh", bvh(zero=True), True, "no size"
    for big in ("1e30", "1e7", "-1e9"):
        yield (f"bvh offset {big}", "motion", "off.bvh", bvh(offsets={"LeftForeArm": f"{big} 0 0"}), True,
               "offset of")
        yield (f"bvh root position {big}", "motion", "pos.bvh", bvh(root_row=f"0 {big} 0 0 0 0"), True,
               "over the limit")
    for bad, why in (("nan", "nan"), ("inf", "inf"), ("-inf", "inf"), ("1e999", "inf"), ("zz", "not a number"),
                     ("1,5", "not a number")):
        yield f"bvh value {bad}", "motion", "v.bvh", bvh(rows=[row(bad)] * 4), True, why
    yield "bvh short rows", "motion", "short.bvh", bvh(rows=["0 0 0"] * 4), True, "has 3 values"
    yield "bvh long rows", "motion", "long.bvh", bvh(rows=[" ".join(["0"] * (per + 3))] * 4), True, "values"
    yield "bvh missing rows", "motion", "miss.bvh", bvh(rows=[row("0")] * 2), True, "holds 2"
    yield ("bvh unknown channel", "motion", "ch.bvh", bvh(channels="Xrotation Yrotation Wrotation"), True,
           "unsupported channel")
    yield "bvh too many joints", "motion", "joints.bvh", bvh(extra_joints=1000, frames=1), True, "joints"
    yield ("bvh budget: about 1000 joints x 8000 frames", "motion", "big.bvh",
           bvh(extra_joints=480, declared="8000", rows=[]), True, "budget")
    yield "bvh no motion", "motion", "nomo.bvh", b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n}\n", True, "MOTION"
    yield ("bvh empty hierarchy", "motion", "empty.bvh", b"HIERARCHY\nMOTION\nFrames: 1\nFrame Time: 0.1\n0\n",
           True, "ROOT")
    yield "bvh long line", "motion", "line.bvh", b"HIERARCHY\nROOT " + b"A" * 70000 + b"\n", True, "longer than"
    valid = bvh(frames=6)
    step = max(1, (len(valid) - 30) // 120)
    for cut in range(20, len(valid) - 10, step):
        yield f"bvh truncated at {cut}", "motion", "cut.bvh", valid[:cut], True, None
    rng = random.Random(11)
    for k in range(120):
        data = bytearray(valid)
        for _ in range(rng.randint(1, 6)):
            data[rng.randrange(len(data))] = rng.choice(b"{}\n -.0123456789eEXYZabc\x00\xff")
        yield f"bvh mutation {k}", "motion", "mut.bvh", bytes(data), False, None


def _gltf_cases() -> Iterator[tuple[str, str, str, bytes, bool]]:
    big = 12_000_000
    yield "accessor without data, huge", "character", "a.gltf", gltf({"accessors": [
        {"componentType": 5126, "type": "VEC4", "count": big}], "animations": [
        {"samplers": [{"input": 0, "output": 0}], "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}]}],
        "nodes": [{}]}), True
    chans = [{"sampler": 0, "target": {"node": 0, "path": "translation"}} for _ in range(200)]
    for count in (2_000_000, 4_000_000):
        yield f"many channels on data-less accessors ({count})", "motion", "ch.gltf", gltf({
            "accessors": [{"componentType": 5126, "type": "SCALAR", "count": count},
                          {"componentType": 5126, "type": "VEC3", "count": count}],
            "animations": [{"samplers": [{"input": 0, "output": 1}], "channels": chans}], "nodes": [{}]}), True
    yield "too many channels", "motion", "ch2.gltf", gltf({
        "accessors": [{"componentType": 5126, "type": "SCALAR", "count": 1}],
        "animations": [{"samplers": [{"input": 0, "output": 0}], "channels": chans * 120}], "nodes": [{}]}), True
    yield "matrix accessor at the element limit", "character", "m.gltf", gltf({
        "accessors": [{"componentType": 5126, "type": "MAT4", "count": 3_000_000}],
        "skins": [{"joints": [0], "inverseBindMatrices": 0}], "nodes": [{}]}), True
    payload = "%00" * 2_000_000
    yield "percent-encoded data URI", "character", "p.gltf", gltf({"buffers": [
        {"byteLength": 2_000_000, "uri": "data:application/octet-stream," + payload}]}), True
    depth = 32_000
    nodes = [{"children": [i + 1]} for i in range(depth - 1)] + [{}]
    yield "32,000 chained nodes, animated leaf", "motion", "deep.gltf", gltf({
        "nodes": nodes, "accessors": [{"componentType": 5126, "type": "SCALAR", "count": 2},
                                      {"componentType": 5126, "type": "VEC3", "count": 2}],
        "animations": [{"samplers": [{"input": 0, "output": 1}],
                        "channels": [{"sampler": 0, "target": {"node": depth - 1, "path": "translation"}}]}]}), True
    yield "node cycle", "character", "cyc.gltf", gltf({"nodes": [{"children": [1]}, {"children": [0]}]}), True
    yield "node two parents", "character", "two.gltf", gltf({"nodes": [{"children": [2]}, {"children": [2]}, {}]}), True
    yield "huge translation", "motion", "tr.gltf", gltf({"nodes": [{"translation": [1e30, 0, 0]}]}), True
    for field, value in (("accessors", 5), ("nodes", "x"), ("buffers", [{"byteLength": -1}]),
                         ("buffers", [{"byteLength": 10, "uri": "file:///etc/passwd"}]),
                         ("buffers", [{"byteLength": 10, "uri": "http://169.254.169.254/"}]),
                         ("buffers", [{"byteLength": 10, "uri": "data:;base64,!!!"}]),
                         ("images", [{"uri": "../../secret.png"}]), ("extensionsRequired", ["KHR_draco_mesh_compression"]),
                         ("skins", [{"joints": [99]}]), ("meshes", [{"primitives": [{"attributes": {"POSITION": 7}}]}])):
        yield f"gltf bad {field} {str(value)[:30]}", "character", "bad.gltf", gltf({field: value, "nodes": [{}]}
                                                                                 if field != "nodes" else {field: value}), True
    for version in ("1.0", "3.0", None, 2):
        yield f"gltf version {version}", "character", "v.gltf", json.dumps({"asset": {"version": version}}).encode(), True
    doc = {"buffers": [{"byteLength": 16}], "bufferViews": [{"buffer": 0, "byteLength": 16}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "type": "VEC3", "count": 100}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}], "nodes": [{"mesh": 0}]}
    yield "accessor past its view", "character", "v.glb", glb(doc, b"\x00" * 16), True
    ok = glb({"nodes": [{}]})
    for cut in range(0, len(ok) - 1, 2):
        yield f"glb truncated at {cut}", "character", "cut.glb", ok[:cut] if cut >= 4 else b"glTF"[:cut] + b"x", True
    yield "glb lying length", "character", "lie.glb", b"glTF" + struct.pack("<II", 2, 2**31) + ok[12:], True
    yield "not json", "character", "nj.gltf", b"{" * 5000, True
    yield "deep json", "character", "dj.gltf", b"[" * 100_000 + b"]" * 100_000, True
    yield "base64 garbage", "character", "b.gltf", gltf({"buffers": [
        {"byteLength": 4, "uri": "data:application/octet-stream;base64," + base64.b64encode(b"ab").decode()}]}), True
    rng = random.Random(7)
    base = json.dumps({"asset": {"version": "2.0"}, **doc}).encode()
    for k in range(200):
        data = bytearray(base)
        for _ in range(rng.randint(1, 5)):
            data[rng.randrange(len(data))] = rng.choice(b'{}[]:,"0123456789-e ')
        yield f"gltf mutation {k}", "character", "mut.gltf", bytes(data), False


def cases() -> list[Case]:
    """Every generated case (at least 500); a glTF case without an expected phrase gets None."""
    gltf_cases = [(*c, None) for c in _gltf_cases()]
    return [*_bvh_cases(), *gltf_cases]  # type: ignore[list-item]
