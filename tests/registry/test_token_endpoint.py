"""GET /api/registry/token on the real daphne: who gets what, and every refusal a 401 or 400, never a 500."""

from __future__ import annotations

import base64

import jwt
import pytest

from registry import services
from registry.tokens import key_id

from .conftest import Account, ask_token, make_fleet

pytestmark = pytest.mark.django_db(transaction=True)


def claims_of(answer) -> dict:
    key = services.signing_key().public_key()
    return jwt.decode(answer.json()["token"], key, algorithms=["ES256"], audience="bridgeos-registry")


def test_alice_gets_push_and_pull_on_her_namespace_with_her_api_token(daphne_server):
    fleet = make_fleet()
    answer = ask_token(
        daphne_server,
        fleet.alice_token,
        "repository:alice/hello:pull,push",
        account="alice",
        client_id="docker",
        offline_token="true",
    )
    assert answer.status_code == 200, answer.text
    body = answer.json()
    # No refresh_token: docker would redeem it with a POST this realm does not serve.
    assert set(body) == {"token", "access_token", "expires_in", "issued_at"}
    assert body["token"] == body["access_token"] and body["expires_in"] == 300
    assert body["issued_at"].endswith("Z")
    assert jwt.get_unverified_header(body["token"])["kid"] == key_id(services.signing_key().public_key())
    claims = claims_of(answer)
    assert claims["iss"] == "bridgeos-cloud" and claims["sub"] == "alice" and claims["aud"] == "bridgeos-registry"
    assert claims["access"] == [{"type": "repository", "name": "alice/hello", "actions": ["pull", "push"]}]


def test_others_namespaces_and_the_catalog_give_an_empty_access(daphne_server):
    fleet = make_fleet()
    for account in (fleet.bob_password, fleet.bob_token, fleet.bob_robot, fleet.alice_robot):
        answer = ask_token(daphne_server, account, "repository:carol/hello:pull,push", "registry:catalog:*")
        assert answer.status_code == 200, answer.text
        assert claims_of(answer)["access"] == []


def test_a_robot_pulls_its_owners_repositories_and_never_pushes(daphne_server):
    fleet = make_fleet()
    answer = ask_token(daphne_server, fleet.alice_robot, "repository:alice/hello:pull,push")
    claims = claims_of(answer)
    assert claims["sub"] == "robot:alice-bot"
    assert claims["access"] == [{"type": "repository", "name": "alice/hello", "actions": ["pull"]}]


def test_staff_may_do_anything_anywhere_and_list_the_catalog(daphne_server):
    fleet = make_fleet()
    answer = ask_token(daphne_server, fleet.ops_token, "repository:bob/x:pull,push", "registry:catalog:*")
    assert claims_of(answer)["access"] == [
        {"type": "repository", "name": "bob/x", "actions": ["pull", "push"]},
        {"type": "registry", "name": "catalog", "actions": ["*"]},
    ]


def test_the_service_asked_for_is_the_audience(daphne_server):
    fleet = make_fleet()
    answer = ask_token(daphne_server, fleet.alice_token, service="other-registry")
    claims = jwt.decode(
        answer.json()["token"], services.signing_key().public_key(), algorithms=["ES256"], audience="other-registry"
    )
    assert claims["aud"] == "other-registry" and claims["access"] == []


def basic(raw: bytes) -> str:
    return "Basic " + base64.b64encode(raw).decode()


@pytest.mark.log_errors()
def test_bad_credentials_are_a_401_with_a_basic_challenge(daphne_server):
    import httpx

    fleet = make_fleet()
    wrong = [
        None,
        "Basic",
        "Basic !!!not-base64!!!",
        "Basic a b c",
        basic(b"no-colon"),
        basic(b"\xff\xfe:\xfd"),
        basic(b"al\x00ice:x"),
        basic(b"alice:brt_\x00"),
        basic(b"nobody:secret-password"),
        basic(b"bob:wrong-password"),
        basic(f"alice:{fleet.bob_token.secret}".encode()),  # Bob's API token under Alice's name
        basic(b"alice:bat_not-a-token"),
        basic(f"alice-bot:{fleet.bob_robot.secret}".encode()),  # Bob's robot token for Alice's robot
        basic(b"no-such-bot:brt_whatever"),
        basic(b"x" * 5000 + b":" + b"y" * 5000),
        "Bearer something",
        f"Token {fleet.bob_token.secret}",
    ]
    for header in wrong:
        headers = {"Authorization": header} if header else {}
        answer = httpx.get(
            f"{daphne_server.url}/api/registry/token", params={"scope": "repository:bob/x:pull"}, headers=headers
        )
        assert answer.status_code == 401, (header, answer.status_code, answer.text)
        assert answer.headers["WWW-Authenticate"] == 'Basic realm="bridgeOS registry"', header


@pytest.mark.parametrize(
    "scope",
    ["repository:alice/hello", "repository::pull", "repository:Alice/Hello:pull", "repository:alice/hello:pull;rm"],
)
def test_a_malformed_scope_is_a_400_that_says_why(daphne_server, scope):
    fleet = make_fleet()
    answer = ask_token(daphne_server, fleet.alice_token, scope)
    assert answer.status_code == 400
    assert "scope" in answer.json() and scope[:20] in answer.json()["scope"][0]


def test_too_many_scopes_are_a_400(daphne_server):
    fleet = make_fleet()
    answer = ask_token(daphne_server, fleet.alice_token, " ".join(f"repository:alice/r{i}:pull" for i in range(60)))
    assert answer.status_code == 400 and "at most 50" in answer.json()["scope"][0]


def test_the_answer_is_the_same_for_every_kind_of_credential(daphne_server):
    fleet = make_fleet()
    for account in (fleet.bob_password, fleet.bob_token):
        claims = claims_of(ask_token(daphne_server, account, "repository:bob/x:pull"))
        assert claims["sub"] == "bob" and claims["access"][0]["actions"] == ["pull"]
    assert Account("bob", "x").creds == "bob:x"
