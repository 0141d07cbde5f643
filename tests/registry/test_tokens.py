"""The token server's pure parts: scopes, grants, claims and libtrust's key id."""

from __future__ import annotations

import base64
import hashlib
import subprocess
from datetime import UTC, datetime

import jwt
import pytest
from hypothesis import given
from hypothesis import strategies as st

from network import pki
from registry.tokens import (
    Principal,
    Scope,
    ScopeError,
    access_claim,
    granted,
    key_id,
    parse_scope,
    sign,
    signing_certificate,
    token_claims,
)

ALICE = Principal("alice")
ALICE_ROBOT = Principal("alice", robot="alice-bot")
OPS = Principal("ops", is_staff=True)
OPS_ROBOT = Principal("ops", is_staff=True, robot="ops-bot")


def libtrust_key_id(der: bytes) -> str:
    """Compute the key id as libtrust's keyIDEncode does, from DER bytes made by openssl rather than our code."""
    encoded = base64.b32encode(hashlib.sha256(der).digest()[:30]).decode().rstrip("=")
    groups = [encoded[i * 4 : i * 4 + 4] for i in range(len(encoded) // 4 - 1)]
    return ":".join([*groups, encoded[(len(encoded) // 4 - 1) * 4 :]])


def test_key_id_is_libtrusts_fingerprint_of_the_der_public_key(tmp_path):
    key = pki.new_key()
    (tmp_path / "key.pem").write_text(pki.key_pem(key))
    der = subprocess.run(
        ["openssl", "pkey", "-in", str(tmp_path / "key.pem"), "-pubout", "-outform", "DER"],
        check=True,
        capture_output=True,
    ).stdout
    kid = key_id(key.public_key())
    assert kid == libtrust_key_id(der)
    assert len(kid.split(":")) == 12 and all(len(group) == 4 for group in kid.split(":"))


def test_a_well_formed_scope_is_parsed_with_colons_in_its_name():
    assert parse_scope("repository:alice/hello:pull,push") == Scope("repository", "alice/hello", ("pull", "push"))
    assert parse_scope("registry:catalog:*") == Scope("registry", "catalog", ("*",))
    assert parse_scope("repository(plugin):host:5000/a:pull").name == "host:5000/a"
    assert parse_scope("repository:alice/hello:pull,pull").actions == ("pull",)


@pytest.mark.parametrize(
    "text",
    [
        "",
        "repository",
        "repository:alice/hello",
        "repository::pull",
        ":alice/hello:pull",
        "repository:alice/hello:",
        "repository:Alice/Hello:pull",
        "repository:alice//hello:pull",
        "repository:alice/hello:pull;push",
        "Repository:alice/hello:pull",
        "repository:" + "a" * 300 + ":pull",
    ],
)
def test_a_malformed_scope_is_refused_with_a_reason(text):
    with pytest.raises(ScopeError, match="scope"):
        parse_scope(text)


@pytest.mark.parametrize(
    ("principal", "scope", "expected"),
    [
        (ALICE, "repository:alice/hello:pull,push", ("pull", "push")),
        (ALICE, "repository:alice/team/hello:push", ("push",)),
        (ALICE, "repository:alice/hello:delete,pull", ("pull",)),
        (ALICE, "repository:bob/hello:pull,push", ()),
        (ALICE, "repository:alice:pull", ()),  # the namespace itself is no repository of hers
        (ALICE, "repository:alicex/hello:pull", ()),
        (ALICE, "registry:catalog:*", ()),
        (ALICE_ROBOT, "repository:alice/hello:push,pull", ("pull",)),
        (ALICE_ROBOT, "repository:bob/hello:pull", ()),
        (OPS, "repository:bob/hello:pull,push,delete", ("pull", "push", "delete")),
        (OPS, "registry:catalog:*", ("*",)),
        (OPS_ROBOT, "repository:bob/hello:pull,push", ("pull",)),
        (OPS_ROBOT, "registry:catalog:*", ()),
        (Principal("alice", is_active=False), "repository:alice/hello:pull", ()),
        (OPS, "repository(plugin):bob/hello:pull", ()),
        (OPS, "registry:other:*", ()),
    ],
)
def test_grants_follow_namespaces_staff_and_robots(principal, scope, expected):
    assert granted(principal, parse_scope(scope)) == expected


NAMES = st.from_regex(r"[a-z0-9]{1,8}(/[a-z0-9]{1,8}){0,2}", fullmatch=True)
PRINCIPALS = st.builds(
    Principal,
    username=st.sampled_from(["alice", "bob"]),
    is_staff=st.booleans(),
    is_active=st.booleans(),
    robot=st.sampled_from([None, "bot"]),
)


@given(PRINCIPALS, NAMES, st.lists(st.sampled_from(["pull", "push", "delete", "*"]), min_size=1, unique=True))
def test_grants_never_exceed_the_request_and_robots_never_push(principal, name, actions):
    got = granted(principal, Scope("repository", name, tuple(actions)))
    assert set(got) <= set(actions)
    if principal.robot:
        assert set(got) <= {"pull"}
    if not principal.is_staff:
        assert not got or name.startswith(principal.username + "/")


def test_the_access_claim_merges_scopes_and_leaves_out_what_was_refused():
    scopes = [parse_scope(s) for s in ["repository:alice/a:pull", "repository:alice/a:push", "repository:bob/b:pull"]]
    assert access_claim(ALICE, scopes) == [{"type": "repository", "name": "alice/a", "actions": ["pull", "push"]}]
    assert access_claim(ALICE, []) == []


def test_a_signed_token_carries_one_audience_string_and_the_key_id():
    key = pki.new_key()
    now = datetime(2026, 1, 1, tzinfo=UTC)
    claims = token_claims(
        ALICE, [parse_scope("repository:alice/a:pull")], issuer="cloud", audience="reg", now=now, ttl_s=300
    )
    token = sign(claims, key)
    assert jwt.get_unverified_header(token) == {"alg": "ES256", "typ": "JWT", "kid": key_id(key.public_key())}
    decoded = jwt.decode(
        token, key.public_key(), algorithms=["ES256"], audience="reg", issuer="cloud", options={"verify_exp": False}
    )
    assert decoded["aud"] == "reg" and decoded["sub"] == "alice"
    assert decoded["exp"] - decoded["iat"] == 300 and decoded["nbf"] == decoded["iat"] == int(now.timestamp())
    assert decoded["access"] == [{"type": "repository", "name": "alice/a", "actions": ["pull"]}]
    assert sign(claims, key) != sign({**claims, "jti": "other"}, key)


def test_the_signing_certificate_carries_the_signing_key():
    key = pki.new_key()
    cert = signing_certificate(key, common_name="t", now=datetime.now(UTC))
    assert key_id(cert.public_key()) == key_id(key.public_key())
