"""The stack the deploy tests share: deployed once per session by `scripts/deploy.sh`, removed afterwards.

It is built and deployed by the project's own command (`make deploy`) under a unique name and free
ports, and removed with its volumes afterwards, failed or not. HAProxy ends TLS there with the
certificate `make deploy` issued from the cloud's CA: every request the tests make, and every agent
(`wss://` with `--ca`), verifies it with that CA, never with verification turned off.
"""

from __future__ import annotations

import functools
import os
import signal
import socket
import ssl
import subprocess
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from tests.conftest import ROOT, free_port

DEPLOY = ROOT / "scripts" / "deploy.sh"
AGENT = ROOT / ".venv" / "bin" / "bridgeos-agent"
# Short, so the test sees a dead replica's robots expire soon; the stack's default is 10 s.
PROCESS_TTL_S = 6.0
PROCESS_HEARTBEAT_S = 1.0


def run(*command: str, timeout: float = 60, env: dict[str, str] | None = None) -> str:
    """Run a command, return its stdout, and fail the test with its output if it fails."""
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env)
    if done.returncode:
        pytest.fail(f"{' '.join(command)} exited {done.returncode}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return done.stdout


def swarm_active() -> bool:
    try:
        state = subprocess.run(
            ["docker", "info", "--format", "{{.Swarm.LocalNodeState}}"], capture_output=True, text=True, timeout=20
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return state.stdout.strip() == "active"


@dataclass
class Agent:
    """One simulated robot's agent: a process from the venv, or a bridgeos/agent container."""

    robot_id: str
    process: subprocess.Popen | None = None
    container: str = ""

    def freeze(self) -> None:
        """Stop the agent dead, sockets open, as a hung robot would be."""
        if self.container:
            run("docker", "pause", self.container)
        else:
            assert self.process is not None
            self.process.send_signal(signal.SIGSTOP)

    def thaw(self) -> None:
        if self.container:
            run("docker", "unpause", self.container)
        else:
            assert self.process is not None
            self.process.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        """Stop the agent for good, frozen or not."""
        if self.container:
            subprocess.run(["docker", "rm", "-f", self.container], capture_output=True, timeout=60, check=False)
            return
        assert self.process is not None
        self.process.send_signal(signal.SIGCONT)  # a frozen agent would not see SIGTERM
        self.process.terminate()
        try:
            self.process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.process.kill()


@dataclass
class Stack:
    """A deployed stack: its name, the load balancer's port, and ways into its containers."""

    name: str
    port: int
    operator_password: str
    secrets: Path
    registry_port: int
    http_port: int
    agents: dict[str, Agent] = field(default_factory=dict)
    output: str = ""  # what `make deploy` printed
    env: dict[str, str] = field(default_factory=dict)  # what it was deployed with

    @functools.cached_property
    def tls(self) -> ssl.SSLContext:
        """Return a context trusting the cloud's CA only, as a robot given `--ca ca.crt` does."""
        return ssl.create_default_context(cadata=(self.secrets / "ca.crt").read_text())

    @functools.cached_property
    def http(self) -> httpx.Client:
        """Return an HTTP client that verifies the stack's TLS with its CA."""
        return httpx.Client(verify=self.tls, timeout=15)

    @property
    def registry(self) -> str:
        """The registry as image references name it (deploy.sh's default: this host's name)."""
        return f"{socket.gethostname()}:{self.registry_port}"

    @property
    def url(self) -> str:
        return f"https://127.0.0.1:{self.port}"

    @property
    def wss(self) -> str:
        return f"wss://127.0.0.1:{self.port}"

    def containers(self, service: str) -> list[str]:
        """Return the ids of the service's running containers."""
        label = f"label=com.docker.swarm.service.name={self.name}_{service}"
        return run("docker", "ps", "-q", "--filter", label).split()

    def exec(self, service: str, *command: str) -> str:
        """Run a command in one of the service's containers."""
        return run("docker", "exec", self.containers(service)[0], *command, timeout=120)

    def sql(self, query: str) -> list[list[str]]:
        """Query the stack's PostgreSQL (inside its container, as the postgres user) and return rows."""
        out = self.exec("postgres", "psql", "-U", "postgres", "-d", "bridgeos", "-tAF", "\t", "-c", query)
        return [line.split("\t") for line in out.splitlines() if line]

    def robots(self) -> dict[str, tuple[bool, str]]:
        """Return {robot id: (connected, the server process holding it)} from the database."""
        rows = self.sql("SELECT id, connected, channel FROM robots_robot ORDER BY id")
        # channels-redis names a consumer's channel `<process prefix>!<suffix>` (robots.presence.process_of).
        return {rid: (connected == "t", channel.partition("!")[0]) for rid, connected, channel in rows}


# One deploy for every deploy test (each costs minutes of CI): session-scoped, shared through conftest.py.
@pytest.fixture(scope="session")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """Deploy the stack with `scripts/deploy.sh` and remove it, volumes included, whatever happens."""
    if not swarm_active():
        pytest.skip("needs dockerd in an active Swarm: scripts/services.sh swarm")
    name = f"bdt{uuid.uuid4().hex[:8]}"
    secrets = tmp_path_factory.mktemp("secrets")
    env = {
        **os.environ,
        "BRIDGEOS_STACK": name,
        "BRIDGEOS_HTTPS_PORT": str(free_port()),
        "BRIDGEOS_HTTP_PORT": str(free_port()),
        "BRIDGEOS_REGISTRY_PORT": str(free_port()),
        "BRIDGEOS_SECRETS_DIR": str(secrets),
        # On this node only: engines other tests join to the Swarm for a while can reach neither the
        # registry under this host's name nor the cloud copies' volume directory.
        # The ROS images' push (about 15 s) is left out: CI's budget is tight and nothing here runs ROS.
        "BRIDGEOS_DEPLOY_ROS_IMAGES": "0",
        "BRIDGEOS_STACK_PLACEMENT": f"node.id == {run('docker', 'info', '--format', '{{.Swarm.NodeID}}').strip()}",
        "DAPHNE_REPLICAS": "2",
        "WORKER_REPLICAS": "1",
        "BRIDGEOS_PROCESS_TTL_S": str(PROCESS_TTL_S),
        "BRIDGEOS_PROCESS_HEARTBEAT_S": str(PROCESS_HEARTBEAT_S),
    }
    deployed = None
    try:
        # Builds whichever stack image is missing or stale (bash docker/build-images.sh stack), then deploys.
        output = run("bash", str(DEPLOY), env=env, timeout=900)
        print("\n".join(line for line in output.splitlines() if line.startswith("deploy:")))
        password = (secrets / "operator_password").read_text().strip()
        deployed = Stack(
            name,
            int(env["BRIDGEOS_HTTPS_PORT"]),
            password,
            secrets,
            int(env["BRIDGEOS_REGISTRY_PORT"]),
            int(env["BRIDGEOS_HTTP_PORT"]),
        )
        deployed.output, deployed.env = output, env
        yield deployed
    finally:
        if deployed:
            deployed.http.close()
        for agent in deployed.agents.values() if deployed else []:
            agent.stop()
        subprocess.run(["bash", str(DEPLOY), "down", "--volumes"], env=env, timeout=180, check=False)


def api_token(stack: Stack) -> str:
    answer = stack.http.post(f"{stack.url}/api/auth", auth=("operator", stack.operator_password))
    assert answer.status_code == 200, answer.text
    return answer.json()["token"]


def wait_until(predicate, timeout: float, what: str, every: float = 0.5):
    """Poll until the predicate returns something truthy; return it, or fail saying what never happened."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := predicate():
            return value
        time.sleep(every)
    pytest.fail(f"{what} within {timeout:g} s")
