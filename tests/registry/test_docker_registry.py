"""The real registry trusts the cloud's tokens: docker and skopeo push and pull by the grants, forged tokens fail."""

from __future__ import annotations

import os
import subprocess
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx
import pytest

from network import pki
from registry import services
from registry.tokens import Principal, parse_scope, sign, token_claims

from .conftest import Account, bearer, make_fleet

# A pushing client asks whether each layer is there first; Distribution logs the "no" at error level.
PUSH_PROBE = r'level=error msg="response completed with error" .*err.code="blob unknown"'
pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]


def run(*args: str, env: dict[str, str] | None = None, stdin: str | None = None) -> subprocess.CompletedProcess:
    """Run a client command, keeping what it printed for the assertion message."""
    return subprocess.run(args, capture_output=True, text=True, env=env, input=stdin, timeout=60)


def push(registry, source: str, target: str, who: Account) -> subprocess.CompletedProcess:
    """Copy a local engine's image into the registry with skopeo, as ``who``."""
    return run(
        "skopeo",
        "copy",
        "--dest-tls-verify=false",
        "--dest-creds",
        who.creds,
        f"docker-daemon:{source}",
        f"docker://{registry.host}/{target}",
    )


def pull(registry, source: str, who: Account, into: Path) -> subprocess.CompletedProcess:
    """Copy an image out of the registry into a local directory with skopeo, as ``who``."""
    return run(
        "skopeo",
        "copy",
        "--src-tls-verify=false",
        "--src-creds",
        who.creds,
        f"docker://{registry.host}/{source}",
        f"dir:{into}",
    )


def refused(done: subprocess.CompletedProcess) -> bool:
    """Tell whether a client failed because the registry refused it (not for any other reason)."""
    said = done.stderr.lower()
    return done.returncode != 0 and any(word in said for word in ("unauthorized", "denied", "authentication required"))


def test_alice_logs_in_with_her_api_token_pushes_and_pulls_back(daphne_server, registry, tiny_image, tmp_path):
    fleet = make_fleet()
    env = {**os.environ, "DOCKER_CONFIG": str(tmp_path / "docker")}
    ref = f"{registry.host}/alice/hello:1"
    login = run(
        "docker", "login", registry.host, "-u", "alice", "--password-stdin", env=env, stdin=fleet.alice_token.secret
    )
    assert login.returncode == 0, login.stderr
    image_id = run("docker", "image", "inspect", "-f", "{{.Id}}", tiny_image).stdout.strip()
    assert run("docker", "tag", tiny_image, ref).returncode == 0
    try:
        pushed = run("docker", "push", ref, env=env)
        assert pushed.returncode == 0, pushed.stderr + pushed.stdout
        assert run("docker", "rmi", ref).returncode == 0
        pulled = run("docker", "pull", ref, env=env)
        assert pulled.returncode == 0, pulled.stderr + pulled.stdout
        assert run("docker", "image", "inspect", "-f", "{{.Id}}", ref).stdout.strip() == image_id
    finally:
        run("docker", "rmi", ref)
        run("docker", "logout", registry.host, env=env)


def test_bob_cannot_pull_push_or_list_alices_repository(daphne_server, registry, tiny_image, tmp_path):
    fleet = make_fleet()
    assert push(registry, tiny_image, "alice/hello:1", fleet.alice_token).returncode == 0
    for bob in (fleet.bob_password, fleet.bob_token, fleet.bob_robot):
        assert refused(pull(registry, "alice/hello:1", bob, tmp_path / bob.secret[:8])), bob
        assert refused(push(registry, tiny_image, "alice/hello:bobs", bob)), bob
        tags = httpx.get(
            f"{registry.url}/v2/alice/hello/tags/list",
            headers=bearer(daphne_server, bob, "repository:alice/hello:pull"),
        )
        assert tags.status_code == 401, tags.text
        catalog = httpx.get(f"{registry.url}/v2/_catalog", headers=bearer(daphne_server, bob, "registry:catalog:*"))
        assert catalog.status_code == 401, catalog.text
    # The operator lists every repository, Alice's among them.
    catalog = httpx.get(
        f"{registry.url}/v2/_catalog", headers=bearer(daphne_server, fleet.ops_token, "registry:catalog:*")
    )
    assert catalog.status_code == 200 and "alice/hello" in catalog.json()["repositories"]


def test_alices_robot_pulls_her_image_with_its_token_but_cannot_push(daphne_server, registry, tiny_image, tmp_path):
    fleet = make_fleet()
    assert push(registry, tiny_image, "alice/hello:1", fleet.alice_token).returncode == 0
    pulled = pull(registry, "alice/hello:1", fleet.alice_robot, tmp_path / "pulled")
    assert pulled.returncode == 0, pulled.stderr
    assert (tmp_path / "pulled" / "manifest.json").exists()
    assert refused(push(registry, tiny_image, "alice/hello:robot", fleet.alice_robot))
    assert refused(pull(registry, "bob/hello:1", fleet.alice_robot, tmp_path / "bobs"))


def forge(key, *, expired: bool = False, kid_of=None) -> str:
    """Sign a token granting pull of alice/hello as the registry expects it, with any key and lifetime."""
    now = datetime.fromtimestamp(time.time() - (3600 if expired else 0), UTC)
    claims = token_claims(
        Principal("alice"),
        [parse_scope("repository:alice/hello:pull")],
        issuer="bridgeos-cloud",
        audience="bridgeos-registry",
        now=now,
        ttl_s=300,
    )
    token = sign(claims, key)
    if kid_of is not None:
        # The header names the cloud's key, the signature is another key's.
        forged = sign(claims, kid_of)
        token = ".".join([forged.split(".")[0], *token.split(".")[1:]])
    return token


def test_the_registry_refuses_forged_and_expired_tokens_and_takes_the_clouds(daphne_server, registry, tiny_image):
    fleet = make_fleet()
    assert push(registry, tiny_image, "alice/hello:1", fleet.alice_token).returncode == 0
    url = f"{registry.url}/v2/alice/hello/tags/list"
    cloud_key, other_key = services.signing_key(), pki.new_key()
    good = httpx.get(url, headers={"Authorization": f"Bearer {forge(cloud_key)}"})
    assert good.status_code == 200 and good.json()["tags"] == ["1"], good.text
    for token in (forge(other_key), forge(other_key, kid_of=cloud_key), forge(cloud_key, expired=True), "garbage"):
        for path in ("/v2/", "/v2/alice/hello/tags/list"):
            answer = httpx.get(registry.url + path, headers={"Authorization": f"Bearer {token}"})
            assert answer.status_code == 401, (path, answer.text)
    assert "invalid token" in registry.log.read_text()
