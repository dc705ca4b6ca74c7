"""Schemathesis (≥ 4) over the sidecar's own OpenAPI schema, against the real stack.

Positive and negative cases for every operation (the SSE stream excepted: it never ends, so a generic
client would wait on it forever; ``test_api`` covers it), with every default check — no 5xx, documented
status codes, content types and response schemas, negative data rejected. Writes carry the bearer token so
the config path is exercised all the way to the classifier; a final test asserts at least 500 cases ran and
none was a server error.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

schemathesis = pytest.importorskip("schemathesis", minversion="4")
from hypothesis import HealthCheck, settings  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402
from schemathesis.specs.openapi.checks import positive_data_acceptance  # noqa: E402

from .stack import Stack, start_stack  # noqa: E402

pytestmark = pytest.mark.integration

TOKEN = "schemathesis-token"
MIN_CASES = 500
_seen: dict[str, int] = {"cases": 0, "server_errors": 0}


@pytest.fixture(scope="module")
def st_stack() -> Iterator[Stack]:
    s = start_stack("sc-st", token=TOKEN)
    yield s
    s.close()


@pytest.fixture(scope="module")
def api_schema(st_stack: Stack):  # noqa: ANN201  (schemathesis' schema type)
    schema = schemathesis.openapi.from_url(f"{st_stack.url}/openapi.json")
    schema.config.generation.update(modes=[GenerationMode.POSITIVE, GenerationMode.NEGATIVE], max_examples=90,
                                    deterministic=True)
    return schema


schema = schemathesis.pytest.from_fixture("api_schema").exclude(path="/v1/events")


def _cross_field_refusal(case, response) -> bool:  # noqa: ANN001
    """A schema-valid config that breaks a rule JSON Schema cannot state — min_window ≤ window_size (checked
    against the config in force for a PATCH or a preset: the `paper` preset's window of 10 under a min_window
    an earlier write raised), ``calibration: file`` needs a ``calibration_file``, and that file must be a
    calibration readable on the classifier's host: a 422 naming the field is the right answer there."""
    write = ((case.path == "/v1/config" and case.method in ("PUT", "PATCH"))
             or (case.path == "/v1/config/preset/{name}" and case.method == "POST"))
    if not write or response.status_code != 422:
        return False
    detail = response.json().get("detail", [])
    return bool(detail) and all("must not exceed window_size" in d.get("msg", "")
                                or "needs calibration_file" in d.get("msg", "")
                                or list(d.get("loc", [])) == ["body", "calibration_file"] for d in detail)


def _stale_if_match(case, response) -> bool:  # noqa: ANN001
    """A write whose ``If-Match`` (schema-valid: any 16 hex digits) names another version than the one in force: a
    412 is the right answer, and the generated tag is almost never the version in force."""
    headers = {k.lower(): v for k, v in (case.headers or {}).items()}
    return response.status_code == 412 and headers.get("if-match", "*") != "*"


@schema.parametrize()
@settings(deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
def test_openapi_contract(case, st_stack: Stack) -> None:  # noqa: ANN001
    response = case.call(headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
    _seen["cases"] += 1
    if response.status_code >= 500:
        _seen["server_errors"] += 1
    refused_rightly = _cross_field_refusal(case, response) or _stale_if_match(case, response)
    excluded = [positive_data_acceptance] if refused_rightly else None
    case.validate_response(response, excluded_checks=excluded)


def test_enough_cases_and_no_server_errors() -> None:
    """Runs after the parametrized test above (pytest keeps file order)."""
    print(f"schemathesis: {_seen['cases']} cases, {_seen['server_errors']} server errors")
    assert _seen["cases"] >= MIN_CASES, _seen
    assert _seen["server_errors"] == 0, _seen
