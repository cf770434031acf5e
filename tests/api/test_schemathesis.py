"""Property-based requests from the OpenAPI schema (schemathesis) to every operation, valid and
invalid, with and without the token: no server error. Its own catalog, as the requests release
versions."""

from __future__ import annotations

import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error

EXAMPLES_PER_OPERATION = 12


def test_no_server_error(populated, broker, auth):
    schema = schemathesis.openapi.from_asgi("/openapi.json", populated.app)
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 15
    for operation in operations:
        # an operation with no parameter and no body (GET /healthz) has no invalid request to make
        modes = (GenerationMode.POSITIVE, GenerationMode.NEGATIVE) if any(operation.iter_parameters()) or (
            operation.get_request_payload_content_types()) else (GenerationMode.POSITIVE,)
        for mode in modes:

            @given(case=operation.as_strategy(generation_mode=mode))
            @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None,
                      derandomize=True, suppress_health_check=list(HealthCheck))
            def no_server_error(case: schemathesis.Case) -> None:
                for headers in ({}, auth):
                    case.call_and_validate(headers=headers, checks=[not_a_server_error])

            no_server_error()
