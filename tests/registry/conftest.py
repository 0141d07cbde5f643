"""A real Distribution registry (Debian's docker-registry) configured by `registry_config` against the test daphne."""

from __future__ import annotations

import base64
import contextlib
import io
import secrets
import shutil
import socket
import subprocess
import tarfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
from django.contrib.auth import get_user_model
from django.core.management import call_command

from network import pki
from robots.services import create_robot, issue_api_token
from tests.conftest import free_port, stop_process
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
        address, _, port = host.rpartition(":")
        _wait_listening(address, int(port), process)
        yield log
    finally:
        stop_process(process)


def _wait_listening(address: str, port: int, process: subprocess.Popen, timeout: float = 30.0) -> None:
    """Wait until the registry accepts on ADDRESS:PORT (not only loopback), failing early if it died."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"docker-registry exited with {process.returncode} before listening on {port}")
        try:
            socket.create_connection((address, port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"docker-registry did not listen on {address}:{port} within {timeout} s")


# Where every Docker engine on this machine looks for a registry's CA (the machine's own and the
# second engines of tests/net/engine.py alike: dockerd has no flag for another directory).
CERTS_D = Path("/etc/docker/certs.d")


@dataclass
class TlsRegistry(Registry):
    """A registry serving HTTPS on a host address, with a certificate of a test CA that engines here trust."""

    ca_pem: str
    ca_file: Path  # alone in its directory: skopeo's --cert-dir reads every *.crt, *.cert and *.key there

    @property
    def url(self) -> str:
        return f"https://{self.host}"

    @property
    def cert_dir(self) -> Path:
        """Return the certs.d directory that makes engines on this machine verify the registry."""
        return CERTS_D / self.host

    def push(self, source: str, target: str, who: Account) -> subprocess.CompletedProcess:
        """Copy an image of this machine's engine into the registry as ``who``, verifying its certificate."""
        trusted = ["--dest-cert-dir", str(self.ca_file.parent), "--dest-creds", who.creds]
        command = ["skopeo", "copy", "--quiet", *trusted, f"docker-daemon:{source}", f"docker://{self.host}/{target}"]
        return subprocess.run(command, capture_output=True, text=True, timeout=300)


@contextlib.contextmanager
def tls_registry(
    daphne_server, base: Path, address: str, *, trust: bool = True, notify: str | None = None
) -> Iterator[TlsRegistry]:
    """Serve a registry over TLS on ``address`` (e.g. the host end of a namespace's link), as robots and nodes see one.

    Its certificate is issued for that IP by a CA made for the run; ``trust`` writes the CA to
    /etc/docker/certs.d/ADDRESS:PORT, so every engine on this machine (second engines in
    namespaces too) pulls from it, and removes it afterwards. Tokens come from ``daphne_server``
    (anything with a ``url``); ``notify`` is registry_config's (``"off"``: no push notifications).
    """
    if shutil.which("docker-registry") is None:
        pytest.skip("docker-registry is not installed: bash scripts/services.sh registry")
    base.mkdir(parents=True, exist_ok=True)
    host = f"{address}:{free_port()}"
    now = datetime.now(UTC)
    ca_key, ca_cert = pki.make_ca("bridgeOS test registry CA", now=now)
    key, cert = pki.issue(ca_key, ca_cert, address, server=True, now=now, names=[address])
    tls, ca_dir = base / "tls", base / "ca"
    tls.mkdir(exist_ok=True)
    ca_dir.mkdir(exist_ok=True)
    (ca_dir / "ca.crt").write_text(pki.pem(ca_cert))
    (tls / "registry.crt").write_text(pki.pem(cert) + pki.pem(ca_cert))
    (tls / "registry.key").write_text(pki.key_pem(key))
    realm = f"{daphne_server.url}/api/registry/token"
    call_command(
        "registry_config",
        realm=realm,
        listen=host,
        storage=str(base / "storage"),
        out=str(base / "conf"),
        tls_cert=str(tls / "registry.crt"),
        tls_key=str(tls / "registry.key"),
        notify=notify,
        stdout=io.StringIO(),  # what it wrote is in base: keep the output of a benchmark to its figures
    )
    registry = TlsRegistry(host, base / "registry.log", realm, ca_pem=pki.pem(ca_cert), ca_file=ca_dir / "ca.crt")
    try:
        if trust:
            registry.cert_dir.mkdir(parents=True, exist_ok=True)
            (registry.cert_dir / "ca.crt").write_text(registry.ca_pem)
        with serving(base / "conf" / "config.yml", host, registry.log):
            yield registry
    finally:
        if trust:
            shutil.rmtree(registry.cert_dir, ignore_errors=True)


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


async def pull_progress(viewer: Any, timeout: float) -> list[dict[str, Any]]:
    """Collect the pull progress a client's live feed shows for a component until the pull is done."""
    from bridgeos_agent.protocol import Event

    progress: list[dict[str, Any]] = []
    while not progress or progress[-1]["done"] < progress[-1]["total"]:
        frame = await viewer.next(Event.COMPONENT_INFORMATION, timeout=timeout)
        pull = frame.data["container"].get("pull")
        if pull:
            progress.append(pull)
    return progress
