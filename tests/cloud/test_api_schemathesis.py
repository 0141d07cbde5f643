"""Fuzz every operation of the OpenAPI schema the live server publishes: no input makes the API fail (5xx)."""

from __future__ import annotations

import pytest
import schemathesis
from drf_spectacular.generators import SchemaGenerator
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error

from .apiutil import SKILL, robot_of, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

# One test per operation; the ids come from the schema built in-process, the cases from the one served.
OPERATIONS = sorted(
    (method.upper(), path)
    for path, operations in SchemaGenerator().get_schema(request=None, public=True)["paths"].items()
    for method in operations
)
REAL_IDS = {"robot_id": "alice-bot", "skill_id": SKILL, "component_id": "sampler"}


@pytest.fixture
def api_token(daphne_server, path) -> str:
    """Alice's API token (she owns alice-bot with the sample Skill, so real ids reach the deep code paths).

    The catalog is written only by staff, so its routes are fuzzed with a staff token to get past the 403.
    """
    alice, token = user_with_token("alice")
    robot_of(alice, "alice-bot")
    return user_with_token("ops", staff=True)[1] if path.startswith("/api/templates") else token


@pytest.fixture
def served_schema(daphne_server):
    return schemathesis.openapi.from_url(daphne_server.url + "/api/schema/?format=json")


@pytest.mark.parametrize(("method", "path"), OPERATIONS, ids=[f"{m} {p}" for m, p in OPERATIONS])
def test_no_request_makes_the_api_fail(daphne_server, served_schema, api_token, method, path):
    operation = served_schema[path][method]
    cases = st.one_of(operation.as_strategy(GenerationMode.POSITIVE), operation.as_strategy(GenerationMode.NEGATIVE))

    @given(case=cases, real_ids=st.booleans())
    @settings(
        max_examples=25,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    def no_server_error(case, real_ids):
        if real_ids:
            # Random ids only ever find nothing (404); half the cases aim at alice's real robot instead.
            for name, value in REAL_IDS.items():
                if name in (case.path_parameters or {}):
                    case.path_parameters[name] = value
        case.call_and_validate(
            base_url=daphne_server.url,
            headers={"Authorization": f"Token {api_token}"},
            checks=[not_a_server_error],
            timeout=10,
        )

    no_server_error()
