"""Generated hostile uploads (no stored blobs): malformed, over-limit and out-of-range BVH and glTF files.

``cases()`` yields (name, kind, file name, bytes, must_fail): ``must_fail`` cases must be refused with a 4xx
naming the problem; the seeded byte mutations of a valid file may also be accepted (they must never be a 5xx).
"""

from __future__ import annotations

import base64
import json
import random
import struct
from collections.abc import Iterator

Case = tuple[str, str, str, bytes, bool]


def bvh(frames: int = 4, frame_time: str = "0.033333", offsets: tuple[str, str] = ("0 10 0", "0 10 0"),
        rows: list[str] | None = None, declared: str | None = None, channels: str = "Xrotation Yrotation Zrotation",
        joints: int = 2) -> bytes:
    """A small BVH: a root with position and rotation channels and a chain of ``joints - 1`` joints."""
    lines = ["HIERARCHY", "ROOT Hips", "{", "  OFFSET 0 0 0",
             "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    for j in range(1, joints):
        lines += [f"  JOINT J{j}", "  {", f"    OFFSET {offsets[j % 2]}", f"    CHANNELS 3 {channels}"]
    lines += ["  End Site", "  {", "    OFFSET 0 5 0", "  }"] + ["  }"] * (joints - 1) + ["}"]
    per = 6 + 3 * (joints - 1)
    body = rows if rows is not None else [" ".join(["0.0"] * per)] * frames
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
    for ft in ("0", "-1", "1e300", "1e-300", "nan", "inf", "abc", "1e-5", "20", "", "0x10"):
        yield f"bvh frame time {ft!r}", "motion", "ft.bvh", bvh(frame_time=ft), True
    for decl in ("0", "-1", "99999999999999999999", "1e3", "12", "x", "3.5"):
        yield f"bvh frames {decl!r}", "motion", "fr.bvh", bvh(declared=decl), True
    yield "bvh zero offsets", "motion", "zero.bvh", bvh(offsets=("0 0 0", "0 0 0")), True
    for big in ("1e30", "1e7", "-1e9"):
        yield f"bvh offset {big}", "motion", "off.bvh", bvh(offsets=(f"0 {big} 0", "0 1 0")), True
        yield f"bvh root position {big}", "motion", "pos.bvh", bvh(rows=[f"0 {big} 0 " + " ".join(["0"] * 6)] * 4), True
    for bad in ("nan", "inf", "-inf", "1e999", "zz", "1,5"):
        yield f"bvh value {bad}", "motion", "v.bvh", bvh(rows=[f"0 0 0 0 0 {bad} 0 0 0"] * 4), True
    yield "bvh short rows", "motion", "short.bvh", bvh(rows=["0 0 0"] * 4), True
    yield "bvh long rows", "motion", "long.bvh", bvh(rows=[" ".join(["0"] * 30)] * 4), True
    yield "bvh missing rows", "motion", "miss.bvh", bvh(rows=[" ".join(["0"] * 9)] * 2), True
    yield "bvh unknown channel", "motion", "ch.bvh", bvh(channels="Xrotation Yrotation Wrotation"), True
    yield "bvh too many joints", "motion", "joints.bvh", bvh(joints=1002, frames=1), True
    yield "bvh budget: 1000 joints x 8000 frames", "motion", "big.bvh", bvh(joints=1000, declared="8000", rows=[]), True
    yield "bvh no motion", "motion", "nomo.bvh", b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n}\n", True
    yield "bvh empty hierarchy", "motion", "empty.bvh", b"HIERARCHY\nMOTION\nFrames: 1\nFrame Time: 0.1\n0\n", True
    yield "bvh long line", "motion", "line.bvh", b"HIERARCHY\nROOT " + b"A" * 70000 + b"\n", True
    valid = bvh(frames=6)
    for cut in range(20, len(valid) - 10, max(1, (len(valid) - 30) // 120)):
        yield f"bvh truncated at {cut}", "motion", "cut.bvh", valid[:cut], True
    rng = random.Random(11)
    for k in range(120):
        data = bytearray(valid)
        for _ in range(rng.randint(1, 6)):
            data[rng.randrange(len(data))] = rng.choice(b"{}\n -.0123456789eEXYZabc\x00\xff")
        yield f"bvh mutation {k}", "motion", "mut.bvh", bytes(data), False


def _gltf_cases() -> Iterator[Case]:
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
    """Every generated case (at least 500)."""
    return [*_bvh_cases(), *_gltf_cases()]
