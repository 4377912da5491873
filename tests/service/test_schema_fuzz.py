"""A bounded schema fuzz run (schemathesis) against the real service: generated requests for every operation of
the OpenAPI document, with a key, and every answer checked: no server error, a status code and content type the
document lists, and a body that matches its documented schema. About a minute (RETARGET_FUZZ_EXAMPLES per
operation)."""

from __future__ import annotations

import os
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, settings
from service_harness import Service

schemathesis = pytest.importorskip("schemathesis")
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

pytestmark = pytest.mark.service

EXAMPLES = int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "12"))
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]


@pytest.fixture(scope="module")
def api_schema(service: Service) -> Any:
    return schemathesis.openapi.from_url(f"{service.base_url}/openapi.json")


@pytest.fixture(scope="module")
def fuzz_key(service: Service) -> dict[str, str]:
    return service.key("fuzz")


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=list(HealthCheck))
def test_fuzzed_requests_get_documented_answers(case: Any, fuzz_key: dict[str, str]) -> None:
    case.call_and_validate(headers=fuzz_key, checks=CHECKS, timeout=30)
