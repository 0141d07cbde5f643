"""A real Distribution registry (Debian's docker-registry) configured by `registry_config` against the test daphne."""

from __future__ import annotations

import base64
import contextlib
import secrets
import shutil
import subprocess
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from django.contrib.auth import get_user_model
from django.core.management import call_command

from robots.services import create_robot, issue_api_token
from tests.conftest import free_port, stop_process, wait_for_port
from tests.logguard import watch

PASSWORD = "correct-horse-battery-42"


@dataclass
class Registry:
    """A registry serving on loopback with plain HTTP, trusting the cloud's token key."""

    host: str
    log: Path
    realm: str

    @property
    def url(self) -> str:
        return f"http://{self.host}"


@pytest.fixture(scope="module")
def registry(daphne_server, tmp_path_factory) -> Iterator[Registry]:
    """Start `docker-registry serve` on a free loopback port with the config registry_config writes."""
    if shutil.which("docker-registry") is None:
        pytest.skip("docker-registry is not installed: bash scripts/services.sh registry")
    base = tmp_path_factory.mktemp("registry")
    host = f"127.0.0.1:{free_port()}"
    realm = f"{daphne_server.url}/api/registry/token"
    call_command(
        "registry_config", realm=realm, listen=host, storage=str(base / "storage"), out=str(base / "conf"), stdout=None
    )
    with serving(base / "conf" / "config.yml", host, base / "registry.log") as log:
        yield Registry(host, log, realm)


@contextlib.contextmanager
def serving(config: Path, host: str, log: Path) -> Iterator[Path]:
    """Run `docker-registry serve CONFIG` until the block ends; its log is read by the log guard."""
    watch(log)
    with log.open("wb") as out:
        process = subprocess.Popen(["docker-registry", "serve", str(config)], stdout=out, stderr=subprocess.STDOUT)
    try:
        wait_for_port(int(host.rpartition(":")[2]), process)
        yield log
    finally:
        stop_process(process)


@dataclass
class Account:
    """Credentials a client presents: a username (or robot id) and a secret."""

    name: str
    secret: str

    @property
    def basic(self) -> str:
        return "Basic " + base64.b64encode(f"{self.name}:{self.secret}".encode()).decode()

    @property
    def creds(self) -> str:
        return f"{self.name}:{self.secret}"


@dataclass
class Fleet:
    """Alice and Bob, each with an API token and a robot; Bob also with a password; an operator."""

    alice_token: Account
    alice_robot: Account
    bob_password: Account
    bob_token: Account
    bob_robot: Account
    ops_token: Account


def make_fleet() -> Fleet:
    """Create the users and robots of a test (committed: daphne reads them)."""
    users = get_user_model().objects
    # Hashing a password costs a good part of a second: only Bob has one.
    alice = users.create_user("alice")
    bob = users.create_user("bob", password=PASSWORD)
    ops = users.create_user("ops", is_staff=True)
    return Fleet(
        alice_token=Account("alice", issue_api_token(alice)[0]),
        alice_robot=Account("alice-bot", create_robot("alice-bot", alice)[1]),
        bob_password=Account("bob", PASSWORD),
        bob_token=Account("bob", issue_api_token(bob)[0]),
        bob_robot=Account("bob-bot", create_robot("bob-bot", bob)[1]),
        ops_token=Account("ops", issue_api_token(ops)[0]),
    )


def ask_token(daphne_server, who: Account | None, *scopes: str, **params: Any) -> httpx.Response:
    """Ask the cloud's realm for a token as a registry client does."""
    headers = {"Authorization": who.basic} if who else {}
    query = [("service", "bridgeos-registry"), *(("scope", s) for s in scopes), *params.items()]
    return httpx.get(f"{daphne_server.url}/api/registry/token", params=query, headers=headers, timeout=10)


def bearer(daphne_server, account: Account, *scopes: str) -> dict[str, str]:
    """Return the Authorization header of a token the realm granted for these scopes."""
    answer = ask_token(daphne_server, account, *scopes)
    assert answer.status_code == 200, answer.text
    return {"Authorization": f"Bearer {answer.json()['token']}"}


@pytest.fixture(scope="module")
def tiny_image(tmp_path_factory) -> str:
    """Import a one-layer image of one small file (unique per run) into the local engine."""
    base = tmp_path_factory.mktemp("image")
    (base / "hello.txt").write_text(f"hello from the registry tests {secrets.token_hex(8)}\n")
    with tarfile.open(base / "rootfs.tar", "w") as tar:
        tar.add(base / "hello.txt", arcname="hello.txt")
    name = f"bridgeos-test/registry-hello:{secrets.token_hex(4)}"
    done = subprocess.run(["docker", "import", str(base / "rootfs.tar"), name], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    yield name
    subprocess.run(["docker", "rmi", "-f", name], capture_output=True)
