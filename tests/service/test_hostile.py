"""The generated hostile-input suite (tests/service/hostile_cases.py, over 500 cases) against the real service:
each refused case is a 4xx whose message names the problem (the one the case targets, when it says) (and no server path or blob name), no case is a
server error, the io worker process never dies, and its peak memory stays under its resting size plus the
parse budget (with a margin)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import httpx
import pytest
from hostile_cases import cases
from service_harness import Service

pytestmark = pytest.mark.service

MARGIN_BYTES = 200 * 1024 * 1024


def children(pid: int) -> list[int]:
    try:
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def status_bytes(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return 0


def test_hostile_uploads_are_refused_with_reasons(service: Service) -> None:
    io = service.procs["io"]
    pool = children(io.pid)
    assert pool, "the io worker has no pool process"
    resting = max(status_bytes(p, "VmRSS") for p in pool)
    http = httpx.Client(base_url=service.base_url, headers=service.key("hostile"), timeout=120)
    failures: list[str] = []
    for name, kind, filename, data, must_fail, expect in cases():
        r = http.post(f"/v1/{'characters' if kind == 'character' else 'motions'}", files={"file": (filename, data)})
        detail = r.json().get("detail", "") if r.headers.get("content-type") == "application/json" else r.text
        if r.status_code >= 500:
            failures.append(f"{name}: {r.status_code} {str(detail)[:200]}")
        elif must_fail and not (400 <= r.status_code < 500 and isinstance(detail, str) and len(detail) > 10):
            failures.append(f"{name}: expected a 4xx with a reason, got {r.status_code} {str(detail)[:200]}")
        elif must_fail and expect and expect.lower() not in str(detail).lower():
            failures.append(f"{name}: refused, but not by the check it targets ({expect!r}): {str(detail)[:200]}")
        elif r.status_code >= 400 and (re.search(r"[0-9a-f]{64}", str(detail)) or str(service.data_dir) in str(detail)):
            failures.append(f"{name}: the message shows a blob name or server path: {str(detail)[:200]}")
    assert io.poll() is None and children(io.pid) == pool, "the io worker or its pool process died"
    peak = max(status_bytes(p, "VmHWM") for p in pool)
    budget = int(os.environ.get("RETARGET_API_PARSE_BUDGET_BYTES", 300 * 1024 * 1024))
    assert peak - resting < budget + MARGIN_BYTES, f"peak {peak >> 20} MiB, resting {resting >> 20} MiB"
    assert not failures, "\n".join(failures[:30]) + f"\n({len(failures)} failures)\n" + service.log_tail()
