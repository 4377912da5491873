"""Two `retarget eval` runs of the same cases side by side: the per-case "all targets met" share, the mean judged
figures and ratios to the copy of the ``full`` method, the misses by target, and the cases that flipped.

    python benchmarks/eval/compare_evals.py BASELINE/eval.json CANDIDATE/eval.json [--method full]
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import Counter
from pathlib import Path
from typing import Any

FIGURES = ("pen_percent", "frames_over_1cm_percent", "contact_preservation", "false_contacts", "foot_accuracy",
           "skate_cm", "ground_penetration_cm", "end_effector_error_cm", "jerk_ratio", "head_percent")  # fmt: skip
RATIOS = ("pen_percent", "frames_over_1cm_percent", "end_effector_error_cm")

Rows = dict[tuple[str, str, str], dict[str, Any]]


def load_rows(path: Path) -> Rows:
    """(method, body, clip) -> the eval.json row."""
    return {(r["method"], r["body"], r["clip"]): r for r in json.loads(path.read_text())["rows"]}


def _mean(values: list[float]) -> float:
    return statistics.mean(values) if values else float("nan")


def summary(rows: Rows, method: str) -> dict[str, Any]:
    """Cases, share meeting every target, mean figures, mean per-case ratios to the copy, misses by target."""
    cases = {k: r for k, r in rows.items() if k[0] == method}
    met = sum(all(r["targets_met"].values()) for r in cases.values())
    means = {f: _mean([r["values"][f] for r in cases.values() if r["values"].get(f) is not None]) for f in FIGURES}
    ratios = {}
    for f in RATIOS:
        pairs = [(r["values"][f], rows[("copy", k[1], k[2])]["values"][f]) for k, r in cases.items()]
        ratios[f] = _mean([v / c for v, c in pairs if v is not None and c])
    misses = Counter(t for r in cases.values() for t, ok in r["targets_met"].items() if not ok)
    return {"cases": len(cases), "all_met": met, "means": means, "ratios": ratios, "misses": dict(misses)}


def flipped(a: Rows, b: Rows, method: str) -> list[str]:
    """The cases meeting every target in one run and not in the other, with the targets missed."""
    out = []
    for k in sorted(set(a) & set(b)):
        if k[0] != method:
            continue
        ma, mb = all(a[k]["targets_met"].values()), all(b[k]["targets_met"].values())
        if ma != mb:
            missed = [t for t, ok in (b if ma else a)[k]["targets_met"].items() if not ok]
            out.append(f"{k[1]} {k[2]}: {'met -> missed' if ma else 'missed -> met'} ({', '.join(missed)})")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("baseline", type=Path)
    ap.add_argument("candidate", type=Path)
    ap.add_argument("--method", default="full")
    a = ap.parse_args()
    rows = {"baseline": load_rows(a.baseline), "candidate": load_rows(a.candidate)}
    for name, r in rows.items():
        s = summary(r, a.method)
        share = 100.0 * s["all_met"] / max(s["cases"], 1)
        print(f"{name}: {s['cases']} cases, all targets met {s['all_met']} ({share:.0f} %)")
        print("  means: " + "  ".join(f"{k} {v:.4g}" for k, v in s["means"].items()))
        print("  ratios to the copy: " + "  ".join(f"{k} {v:.3f}" for k, v in s["ratios"].items()))
        print(f"  misses: {s['misses']}")
    for line in flipped(rows["baseline"], rows["candidate"], a.method):
        print(line)


if __name__ == "__main__":
    main()
