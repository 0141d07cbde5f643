"""The generated role matrix: every door of the cloud as every role and none, on its own organization and another's."""

from __future__ import annotations

import pytest

from tests.teams.matrix import run_matrix, unruled

pytestmark = pytest.mark.django_db(transaction=True)


def test_every_route_method_and_client_event_has_a_rule():
    assert unruled() == []


def test_every_door_answers_every_role_exactly_as_its_rule_says(daphne_server):
    result = run_matrix(daphne_server.ws_url)
    assert not result["failed"], "\n".join(result["failed"])
    assert result["violations"] == 0
    # Every route x method x caller x organization, the client's requests and the bridges' handshakes.
    assert result["cases"] > 1500
