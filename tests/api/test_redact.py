"""Messages lose server paths and blob names, in time linear in their length."""

from __future__ import annotations

import pytest

from api.redact import redact, redact_all

SHA = "0123456789abcdef" * 4


@pytest.mark.parametrize(("text", "expected"), [
    (f"/srv/data/blobs/01/{SHA}.bvh: line 3: bad", "walk.bvh: line 3: bad"),
    (f"cannot read '{SHA}.glb' (truncated)", "cannot read 'walk.bvh' (truncated)"),
    (f"({'f' * 64}.fbx)", "(the file)"),
    ("/tmp/work/x/metrics.json was not written", "metrics.json was not written"),
    ("a trailing slash: /a/b/ stays a path", "a trailing slash: b/ stays a path"),
    ("one part /x and //y stay", "one part /x and //y stay"),
    ("file:/srv/data/x.bvh:12", "file:x.bvh:12"),
])
def test_paths_and_blob_names_are_replaced(text: str, expected: str) -> None:
    assert redact(text, {SHA: "walk.bvh"}) == expected


def test_nested_values_are_redacted() -> None:
    value = {"warnings": [f"/a/b/{SHA}.bvh odd"], "n": 3}
    assert redact_all(value, {SHA: "clip.bvh"}) == {"warnings": ["clip.bvh odd"], "n": 3}


@pytest.mark.timeout(10)
@pytest.mark.parametrize("unit", ["J", "/a", "/" + "a" * 63, "a" * 63 + "/", "0a"])
def test_long_tokens_take_linear_time(unit: str) -> None:
    """A 60,000-character joint name in a message once took about half a minute (a pattern tried at every start):
    the timeout is the bound (no wall-clock assert: shared machines)."""
    text = unit * (60_000 // len(unit))
    assert redact(f"joint {text!r} not found", {SHA: "x"}).endswith("not found")
