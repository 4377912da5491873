"""A bounded schema fuzz run (schemathesis) against the real service: generated requests for every operation of
the OpenAPI document, with a key, and every answer checked: no server error, a status code and content type the
document lists, and a body that matches its documented schema. About a minute (RETARGET_FUZZ_EXAMPLES per
operation)."""

from __future__ import annotations

import os
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from service_harness import Service

schemathesis = pytest.importorskip("schemathesis")
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

pytestmark = pytest.mark.service

EXAMPLES = int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "25"))
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]


def test_fuzzed_requests_get_documented_answers(service: Service) -> None:
    schema = schemathesis.openapi.from_url(f"{service.base_url}/openapi.json")
    key = service.key("fuzz")
    failures: list[str] = []
    operations = 0
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                  phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
        def run(case: Any) -> None:
            try:
                case.call_and_validate(headers=key, checks=CHECKS, timeout=60)
            except Exception as exc:  # collect every operation's failures, not only the first
                failures.append(f"{case.method} {case.formatted_path}: {str(exc)[:400]}")

        run()
    assert operations > 20
    assert not failures, f"{len(failures)} failures:\n" + "\n".join(failures[:20])
