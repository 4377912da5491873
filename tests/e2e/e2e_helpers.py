"""Helpers of the browser tests: pixels of the WebGL views, waiting for renders, layout checks."""

from __future__ import annotations

from typing import Any

import numpy as np

VIEWS = ("source", "before", "after")
LAPTOP = {"width": 1366, "height": 768}
WIDE = {"width": 2560, "height": 1080}

_PIXELS_JS = """(name) => {
  const c = document.querySelector(`canvas[data-view="${name}"]`);
  if (!c || !c.width || !c.height) return null;
  const w = 192, h = Math.max(1, Math.round(192 * c.height / c.width));
  const tmp = document.createElement('canvas');
  tmp.width = w; tmp.height = h;
  const ctx = tmp.getContext('2d');
  ctx.drawImage(c, 0, 0, w, h);
  const d = ctx.getImageData(0, 0, w, h).data;
  const lum = new Array(w * h);
  const red = new Array(w * h);
  for (let i = 0; i < w * h; i++) {
    const r = d[4 * i], g = d[4 * i + 1], b = d[4 * i + 2];
    lum[i] = Math.round(0.299 * r + 0.587 * g + 0.114 * b);
    red[i] = r - Math.max(g, b) > 60 ? 1 : 0;
  }
  return { w, h, lum, red };
}"""


def view_pixels(page: Any, name: str) -> np.ndarray:
    """Luminance ``(H, W)`` of a view's WebGL canvas (drawn into a 2D canvas in the page, downscaled)."""
    out = page.evaluate(_PIXELS_JS, name)
    assert out is not None, f"no canvas for the {name} view"
    return np.asarray(out["lum"], dtype=np.int16).reshape(out["h"], out["w"])


def red_fraction(page: Any, name: str) -> float:
    """Share of a view's pixels that are clearly red (penetration highlights, contact markers)."""
    out = page.evaluate(_PIXELS_JS, name)
    assert out is not None, f"no canvas for the {name} view"
    return float(np.asarray(out["red"]).mean())


def bright_fraction(lum: np.ndarray, threshold: int = 140) -> float:
    """Share of pixels brighter than the dark background and grid (the light grey character)."""
    return float((lum > threshold).mean())


def changed_fraction(a: np.ndarray, b: np.ndarray, threshold: int = 30) -> float:
    """Share of pixels whose luminance changed by more than ``threshold``."""
    return float((np.abs(a - b) > threshold).mean())


def seek(page: Any, frame: int) -> None:
    """Seek through the test hook and wait until every loaded view has drawn again. The render counts are read in
    the same script as the seek: a draw already due (a camera still settling) then cannot pass for the new frame's."""
    before = page.evaluate(
        """(f) => { const counts = Object.fromEntries(Object.entries(window.__viewer.views())
                      .filter(([, v]) => v.loaded).map(([k, v]) => [k, v.renders || 0]));
                    window.__viewer.seek(f); return counts; }""",
        frame,
    )
    wait_drawn(page, before)


def wait_drawn(page: Any, before: dict[str, int], timeout: float = 15_000) -> None:
    page.wait_for_function(
        """(before) => { const v = window.__viewer.views();
            return Object.entries(before).every(([k, n]) => v[k].renders > n); }""",
        arg=before,
        timeout=timeout,
    )


def view_frames(page: Any) -> dict[str, int]:
    """The frame each view shows, from its own mixer (test hook) and from its data-frame attribute."""
    hook = page.evaluate(
        "Object.fromEntries(Object.entries(window.__viewer.views()).filter(([, v]) => v.loaded).map(([k, v]) => [k, v.frame]))"
    )
    attrs = page.evaluate(
        "Object.fromEntries([...document.querySelectorAll('.view[data-view] .view-box[data-frame]')].map((b) => [b.closest('.view').dataset.view, Number(b.dataset.frame)]))"
    )
    assert hook == attrs, f"test hook {hook} and data-frame attributes {attrs} disagree"
    return dict(hook)


def overflow(page: Any) -> dict[str, float]:
    """Page size against the viewport (a horizontal scroll bar means the layout overflows)."""
    return dict(
        page.evaluate(
            "({sw: document.documentElement.scrollWidth, sh: document.documentElement.scrollHeight, w: innerWidth, h: innerHeight})"
        )
    )


def boxes_in_viewport(page: Any, selector: str) -> list[dict[str, float]]:
    """Bounding boxes of the elements matching ``selector`` that stick out of the viewport horizontally."""
    return list(
        page.evaluate(
            """(sel) => [...document.querySelectorAll(sel)].map((e) => e.getBoundingClientRect())
             .filter((r) => r.left < -0.5 || r.right > innerWidth + 0.5 || r.width < 1 || r.height < 1)
             .map((r) => ({left: r.left, right: r.right, width: r.width, height: r.height}))""",
            selector,
        )
    )
