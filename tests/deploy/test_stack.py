"""The deployed stack: docker/stack.yml on this machine's Swarm, two daphne replicas behind HAProxy.

The stack runs its own image registry (TLS from the cloud's CA) and pulls its images from it by digest;
its worker runs cloud copies as Swarm services through the Docker API proxy, never the raw socket.

The stack (tests/deploy/deployed.py) is deployed once by `make deploy`'s script for every test here.
Real agents (`bridgeos-agent run --simulate --ca`, over `wss://`, half of them from the bridgeos/agent
image) connect through the load balancer; the test then checks, through the same door an operator uses, that the replicas
behave as one cloud, and that killing one (`docker kill`) loses and duplicates nothing.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import socket
import sqlite3
import ssl
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from bridgeos_agent.link import Link
from bridgeos_agent.protocol import Event
from tests.deploy.deployed import (
    AGENT,
    PROCESS_HEARTBEAT_S,
    PROCESS_TTL_S,
    Agent,
    Stack,
    api_token,
    run,
    wait_until,
)

pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(900)]

ROBOTS = 4


def start_agents(stack: Stack, tmp_path: Path) -> dict[str, Path]:
    """Create robots in the stack and start a simulated agent for each; return their data dirs.

    Every other agent runs from the bridgeos/agent image, the rest from this checkout's venv.
    """
    data_dirs = {}
    for n in range(ROBOTS):
        robot_id = f"deploy-{n}"
        token = stack.exec("daphne", "bridgeos-cloud", "manage", "create_robot", robot_id, "--owner", "operator")
        data_dir = tmp_path / robot_id
        data_dir.mkdir()
        # The CA `make deploy` printed, as a robot owner copies it next to the agent.
        ca = data_dir / "ca.crt"
        ca.write_text((stack.secrets / "ca.crt").read_text())
        ca.chmod(0o644)
        args = ["run", "--master", stack.wss, "--robot", robot_id, "--token", token.strip()]
        args += ["--runtime", "process", "--simulate", "--ca", "/data/ca.crt" if n % 2 else str(ca)]
        if n % 2:
            data_dir.chmod(0o777)  # the image's agent runs as its own unprivileged user
            container = run(
                "docker", "run", "-d", "--network", "host", "--name", f"{stack.name}-{robot_id}",
                "-v", f"{data_dir}:/data", "bridgeos/agent:latest", *args, "--data-dir", "/data",
            ).strip()  # fmt: skip
            stack.agents[robot_id] = Agent(robot_id, container=container)
        else:
            with (tmp_path / f"{robot_id}.log").open("ab") as log:
                process = subprocess.Popen(
                    [str(AGENT), *args, "--data-dir", str(data_dir)], stdout=log, stderr=subprocess.STDOUT
                )
            stack.agents[robot_id] = Agent(robot_id, process=process)
        data_dirs[robot_id] = data_dir
    return data_dirs


def outbox_through(data_dir: Path) -> int:
    """Return the sequence number of the last frame an agent put in its outbox (acked frames leave it)."""
    with sqlite3.connect(f"file:{data_dir / 'outbox.sqlite3'}?mode=ro", uri=True, timeout=5) as db:
        row = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'outbox'").fetchone()
    return row[0] if row else 0


def owed_up_to(data_dir: Path, seq: int) -> int:
    """Return how many frames up to seq the agent still waits to see acknowledged."""
    with sqlite3.connect(f"file:{data_dir / 'outbox.sqlite3'}?mode=ro", uri=True, timeout=5) as db:
        return db.execute("SELECT count(*) FROM outbox WHERE seq <= ?", (seq,)).fetchone()[0]


async def live_robots(stack: Stack, token: str, seconds: float) -> tuple[set[str], str]:
    """Watch /ws/client/ through the load balancer; return the robots whose metrics arrived, and the replica."""
    link = Link(f"{stack.wss}/ws/client/", ssl_context=stack.tls)
    await link.connect(Event.AUTHENTICATION_CLIENT, {"token": token})
    replica = link.ws.response.headers.get("X-Bridgeos-Replica", "")
    seen: set[str] = set()
    deadline = time.monotonic() + seconds
    try:
        while (left := deadline - time.monotonic()) > 0 and len(seen) < ROBOTS:
            try:
                frame = await link.next(timeout=left)
            except TimeoutError:
                break
            if frame.event == Event.METRICS and frame.data.get("robot"):
                seen.add(frame.data["robot"])
    finally:
        await link.close()
    return seen, replica


def test_two_replicas_behind_the_load_balancer_act_as_one_cloud(stack: Stack, tmp_path: Path) -> None:
    daphnes = stack.containers("daphne")
    assert len(daphnes) == 2, "the stack runs two daphne replicas"
    data_dirs = start_agents(stack, tmp_path)

    def fleet() -> dict[str, tuple[bool, str]]:
        """This test's robots (other tests' share the stack)."""
        return {rid: state for rid, state in stack.robots().items() if rid in data_dirs}

    # Robots spread over both replicas (the least-connections balance), each held by exactly one.
    robots = wait_until(
        lambda: (r := fleet()) and all(c for c, _ in r.values()) and len(r) == ROBOTS and r,
        60,
        "every robot connected through the load balancer",
    )
    processes = {process for _, process in robots.values()}
    assert len(processes) == 2, f"robots on both replicas: {robots}"

    # A REST command through the load balancer reaches each robot from both replicas, and its reply comes back.
    token = api_token(stack)
    headers = {"Authorization": f"Token {token}"}
    for robot_id in robots:
        served_by: set[str] = set()
        for _ in range(20):
            answer = stack.http.post(f"{stack.url}/api/robot/{robot_id}/start", headers=headers)
            assert answer.status_code == 200, answer.text
            assert answer.json()["accepted"] is True, answer.json()
            served_by.add(answer.headers["X-Bridgeos-Replica"])
            if len(served_by) == 2:
                break
        # Each robot sits on one replica, so one of the two answers crossed between processes.
        assert len(served_by) == 2, f"{robot_id}'s commands were all served by {served_by}"

    # A dashboard client on one replica sees live frames of the robots on both.
    seen, client_replica = asyncio.run(live_robots(stack, token, 30))
    assert seen == set(robots), f"client on {client_replica} saw metrics of {seen} only"

    # Freeze one robot on each replica: a frozen agent cannot reconnect, so only the surviving
    # replica's sweep of the dead process can make its `connected` state honest.
    frozen = {process: min(rid for rid, (_, p) in robots.items() if p == process) for process in processes}
    for robot_id in frozen.values():
        stack.agents[robot_id].freeze()
    # Kill one replica while the other robots stream metrics.
    victim = daphnes[0]
    run("docker", "kill", victim)
    killed_at = time.monotonic()

    def settled() -> tuple[dict[str, tuple[bool, str]], str] | None:
        """The state once the victim's live robots moved and its frozen robot went offline, else None."""
        now = fleet()
        dead = {robots[rid][1] for rid, (connected, process) in now.items() if connected and process != robots[rid][1]}
        if len(dead) != 1:
            return None
        (dead_process,) = dead
        for robot_id, (connected, process) in now.items():
            expected_online = robot_id != frozen[dead_process]
            if connected != expected_online or (connected and process == dead_process):
                return None
        return now, dead_process

    # The sweep runs on the survivors' heartbeat: the dead process's frozen robot is offline within its TTL.
    limit = PROCESS_TTL_S + 2 * PROCESS_HEARTBEAT_S + 3
    after, dead_process = wait_until(settled, limit, "the dead replica's robots moved or marked offline", every=0.25)
    settled_s = time.monotonic() - killed_at
    moved = {rid for rid, (connected, process) in after.items() if connected and process != robots[rid][1]}
    assert moved == {rid for rid, (_, process) in robots.items() if process == dead_process} - {frozen[dead_process]}
    survivor_frozen = frozen[next(p for p in processes if p != dead_process)]
    assert after[survivor_frozen] == robots[survivor_frozen], "a robot on the live replica was left alone"
    print(f"robots before the kill {robots}, after {after}; settled {settled_s:.1f} s after the kill")

    # Thawed, the dead replica's frozen robot finds its socket closed and reconnects to a live replica.
    for robot_id in frozen.values():
        stack.agents[robot_id].thaw()
    wait_until(
        lambda: all(c and p != dead_process for c, p in fleet().values()),
        60,
        "every robot connected again to a live replica",
    )

    # Every frame an agent queued up to now (the kill and the reconnection included) gets acknowledged,
    # and an acknowledgement comes only after the points are committed: none was lost.
    marks = {rid: outbox_through(d) for rid, d in data_dirs.items()}
    wait_until(
        lambda: all(owed_up_to(data_dirs[rid], seq) == 0 for rid, seq in marks.items()),
        60,
        "every frame sent across the kill acknowledged",
    )
    # And none was stored twice, though frames in flight at the kill were resent to the other replica.
    duplicates = stack.sql(
        "SELECT robot_id, name, skill, component, ts, count(*) FROM monitoring_metric "
        "GROUP BY robot_id, name, skill, component, ts, labels::text HAVING count(*) > 1 LIMIT 5"
    )
    assert duplicates == [], f"points stored twice: {duplicates}"
    points = {rid: int(n) for rid, n in stack.sql("SELECT robot_id, count(*) FROM monitoring_metric GROUP BY 1")}
    assert set(points) == set(robots) and all(points.values()), points
    print(f"points stored per robot {points}; frames acknowledged through outbox seq {marks}")

    # The killed task is replaced by Swarm, and the stack is whole again behind the same address.
    wait_until(
        lambda: len(stack.containers("daphne")) == 2 and victim not in stack.containers("daphne"),
        90,
        "Swarm replaced the killed replica",
    )
    health = stack.http.get(f"{stack.url}/api/health")
    assert health.status_code == 200 and json.loads(health.text)["status"] == "ok"


# Asked from inside the worker, as a compromised cloud process would: the proxy must refuse it.
PRIVILEGED_CREATE = """
import json, urllib.error, urllib.request
body = json.dumps({"Image": "bridgeos/base:bookworm", "HostConfig": {"Privileged": True}}).encode()
request = urllib.request.Request("http://docker-proxy:2375/v1.41/containers/create", body,
                                 {"Content-Type": "application/json"})
try:
    urllib.request.urlopen(request, timeout=10)
    print(200)
except urllib.error.HTTPError as exc:
    print(exc.code, json.load(exc)["message"])
"""


def service_spec(service: str) -> dict:
    return json.loads(run("docker", "service", "inspect", "--format", "{{json .Spec}}", service))


def test_the_stack_pulls_from_its_own_registry_and_runs_cloud_copies_through_the_proxy(
    stack: Stack, tmp_path: Path
) -> None:
    # The registry serves TLS verified with the cloud's CA (the one the database holds, which robots pin),
    # under this host's name and 127.0.0.1, and sends clients to the cloud for tokens.
    ca = (stack.secrets / "ca.crt").read_text()
    held = stack.sql("SELECT md5(btrim(cert_pem, E' \\n')) FROM network_authority WHERE name = 'ca'")
    assert held == [[hashlib.md5(ca.strip().encode()).hexdigest()]], "the cloud adopted the stack's CA"
    trusted = ssl.create_default_context(cadata=ca)
    for host in (socket.gethostname(), "127.0.0.1"):
        answer = httpx.get(f"https://{host}:{stack.registry_port}/v2/", verify=trusted, timeout=10)
        assert answer.status_code == 401
        assert (
            f'realm="https://{socket.gethostname()}:{stack.port}/api/registry/token"'
            in answer.headers["www-authenticate"]
        )
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        httpx.get(f"https://127.0.0.1:{stack.registry_port}/v2/", timeout=10)

    # Every service but the registry runs an image of the stack's registry, pinned by digest, and the
    # registry holds it (a token from the cloud, then the manifest by that digest).
    for service in ("daphne", "worker", "beat", "postgres", "redis", "lb", "docker-proxy"):
        image = service_spec(f"{stack.name}_{service}")["TaskTemplate"]["ContainerSpec"]["Image"]
        repository, _, digest = image.partition("@")
        assert repository.startswith(f"{stack.registry}/bridgeos/") and digest.startswith("sha256:"), image
        path = repository.removeprefix(f"{stack.registry}/")
        token = stack.http.get(
            f"{stack.url}/api/registry/token",
            params={"service": "bridgeos-registry", "scope": f"repository:{path}:pull"},
            auth=("operator", stack.operator_password),
        ).json()["token"]
        manifest = httpx.head(
            f"https://127.0.0.1:{stack.registry_port}/v2/{path}/manifests/{digest}",
            headers={
                "Authorization": f"Bearer {token}",
                "Accept": "application/vnd.docker.distribution.manifest.v2+json",
            },
            verify=trusted,
            timeout=10,
        )
        assert manifest.status_code == 200, f"{service}: {image} not in the registry ({manifest.status_code})"

    # The worker has no Docker socket, only the proxy, and the proxy refuses a privileged container.
    worker = service_spec(f"{stack.name}_worker")["TaskTemplate"]["ContainerSpec"]
    assert not [m for m in worker.get("Mounts", []) if "docker.sock" in m["Source"]]
    env = dict(item.split("=", 1) for item in worker["Env"])
    assert env["DOCKER_HOST"] == "tcp://docker-proxy:2375" and env["BRIDGEOS_CLOUD_RUNTIME"] == "swarm"
    refused = stack.exec("worker", "python3", "-c", PRIVILEGED_CREATE)
    assert refused.startswith("403 POST /containers/create with HostConfig.Privileged"), refused

    # A user's image pushed to the stack's registry runs as a cloud copy: a Swarm service from its digest.
    began = time.monotonic()
    client_env = {**os.environ, "DOCKER_CONFIG": str(stack.secrets / "docker")}
    image = f"{stack.registry}/operator/ticker:1"
    run("docker", "tag", "bridgeos/base:bookworm", image)
    run("docker", "push", "-q", image, env=client_env, timeout=120)
    robot_id = "deploy-cloud"
    token = stack.exec("daphne", "bridgeos-cloud", "manage", "create_robot", robot_id, "--owner", "operator").strip()
    (tmp_path / "agent").mkdir()
    with (tmp_path / "agent.log").open("ab") as log:
        args = ["run", "--master", stack.wss, "--ca", str(stack.secrets / "ca.crt"), "--robot", robot_id]
        args += ["--token", token]
        args += ["--runtime", "process", "--simulate", "--data-dir", str(tmp_path / "agent")]
        process = subprocess.Popen(
            [str(AGENT), *args],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    stack.agents[robot_id] = Agent(robot_id, process=process)
    headers = {"Authorization": f"Token {api_token(stack)}"}
    ticker = {"name": "Tick", "location": "cloud", "ros": False}
    # sleep ends at once on the SIGTERM the copy's init passes on, so stopping it takes no grace period.
    ticker["cloud"] = {"image": image, "command": ["sleep", "3600"]}
    config = {"skill": "Ticker", "skill_id": "ticker", "components": {"tick": ticker}}
    added = stack.http.post(f"{stack.url}/api/robot/{robot_id}/skill/add", json={"config": config}, headers=headers)
    assert added.status_code in (200, 201), added.text
    pinned = added.json()["config"]["components"]["tick"]["cloud"]["image"]
    assert pinned.startswith(f"{image}@sha256:"), pinned
    wait_until(lambda: stack.robots().get(robot_id, (False,))[0], 30, "the robot connected")
    started = stack.http.post(
        f"{stack.url}/api/robot/{robot_id}/skill/ticker/start", params={"wait": 10}, headers=headers, timeout=20
    )
    assert started.status_code == 200 and started.json()["accepted"], started.text
    info_url = f"{stack.url}/api/robot/{robot_id}/skill/ticker/component/tick/info"
    info = wait_until(
        lambda: (i := stack.http.get(info_url, headers=headers).json())["status"] == "running" and i,
        60,
        "the cloud copy running",
    )
    assert info["container"]["cloud"]["runtime"] == "swarm"
    print(
        f"pushed, added, started and running as a Swarm service {time.monotonic() - began:.1f} s after the push began"
    )
    services = json.loads(run("docker", "service", "ls", "--format", "{{json .}}", "--filter", f"name=bos-{robot_id}"))
    spec = service_spec(services["Name"])
    assert spec["TaskTemplate"]["ContainerSpec"]["Image"] == pinned
    # ... created by the worker through the proxy, which logs each write it forwards.
    logs = ["docker", "service", "logs", f"{stack.name}_docker-proxy"]
    proxy_log = subprocess.run(logs, capture_output=True, text=True, timeout=60, check=True).stderr  # Python logs there
    assert "POST /services/create" in proxy_log and "refused" in proxy_log

    stopped = stack.http.post(
        f"{stack.url}/api/robot/{robot_id}/skill/ticker/stop", params={"wait": 10}, headers=headers, timeout=20
    )
    assert stopped.status_code == 200, stopped.text
    wait_until(
        lambda: not run("docker", "service", "ls", "-q", "--filter", f"name=bos-{robot_id}").strip(),
        60,
        "the cloud copy's service removed",
    )
    print(f"stopped and removed {time.monotonic() - began:.1f} s after the push began")
