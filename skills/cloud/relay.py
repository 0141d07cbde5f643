"""A cloud relay per robot Skill: cloud-side routing, run and supervised by the cloud's workers.

Modelled on the per-robot ROS master (masters.py): a robot that logs in with a ROS master gets,
for each of its Skills with components allowed in the cloud, a ``CloudRelay`` row (a control port
of the cloud host and a random nonce) and its relay's URL and token in the login answer; a worker
task runs ``python -m bridgeos_agent.router.cloudrelay`` for it on the robot's ROS master, the
reconciler starts it again when it died and stops it once its Skill, its robot or its last
cloud-capable component is gone. One relay per Skill, not per robot: the relay routes one
Skill config and the agent's router (one per Skill) links to one relay.

Process-only: the relay runs as a process group of the cloud host whatever the cloud runtime
(marked as the process runtime's copies are, so any worker finds it again). It is the robot's
ROS node on its master, like the cloud's host-networked copies, and needs nothing but the
agent's Python package the worker already has.

The token is never stored: HMAC(SECRET_KEY, robot, Skill, nonce), so every cloud process derives
the same one, a database dump alone does not yield it, and a new relay (a new nonce) gets a new
one. It reaches the relay in its environment (not its command line, which every user can read)
and the robot only in the login answer on its authenticated WebSocket.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import os
import secrets
import socket
import sys

from django.conf import settings
from django.db.models import Exists, OuterRef

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.runtime.base import ComponentSpec, ComponentState, RuntimeFailure, Status
from bridgeos_agent.runtime.process import ProcessRuntime
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec

from ..models import CloudRelay, Component, Skill
from .orchestration import LaunchFailed, TryAgain, enqueue_on_commit, with_runtime
from .perrobot import Service, converge, report, tcp_answers
from .process import CloudProcessRuntime, _key, _marked
from .runtime import NO_RESTARTS, CloudRuntime, Observed

logger = logging.getLogger(__name__)

KIND_CLOUD_RELAY = "cloud-relay"
RELAY_COMPONENT = "cloudrelay"  # the component id a relay is known by in its marker
CLOUD_LOCATIONS = ("cloud", "either")


def relays_for(robot_id: str, master: str | None) -> dict[str, dict[str, str]]:
    """Return {skill: {url, token}} of a connecting robot's relays (in the caller's transaction), started on commit."""
    if not master:
        return {}  # a relay is a node on the robot's ROS master
    skills = Skill.objects.filter(robot_id=robot_id, components__location__in=CLOUD_LOCATIONS).distinct()
    return {skill.skill_id: _relay_of(skill) for skill in skills}


def relay_for_skill(skill: Skill) -> dict[str, str] | None:
    """Return {url, token} of the relay a Skill started while its robot is connected uses (None: it needs none).

    In the caller's transaction; the relay is started on commit, as at a login.
    """
    if not skill.robot.ros_master or not skill.components.filter(location__in=CLOUD_LOCATIONS).exists():
        return None
    return _relay_of(skill)


def _relay_of(skill: Skill) -> dict[str, str]:
    relay = CloudRelay.objects.select_for_update().filter(skill=skill).first()
    if relay is None:
        relay = CloudRelay.objects.create(
            skill=skill, port=_free_port(), nonce=secrets.token_hex(16), status=CS.PENDING
        )
    enqueue_on_commit("ensure_cloud_relay", skill.robot_id, skill.skill_id)
    return {"url": relay_url(relay.port), "token": relay_token(skill.robot_id, skill.skill_id, relay)}


def relay_url(port: int) -> str:
    """Return the control URL of a relay on the cloud host."""
    return f"http://{settings.BRIDGEOS['CLOUD_HOST']}:{port}"


def relay_token(robot_id: str, skill_id: str, relay: CloudRelay) -> str:
    """Derive a relay's token from SECRET_KEY and its nonce."""
    message = f"cloud-relay\0{robot_id}\0{skill_id}\0{relay.nonce}".encode()
    digest = hmac.new(settings.SECRET_KEY.encode(), message, hashlib.sha256).digest()
    return base64.urlsafe_b64encode(digest).decode().rstrip("=")


def wanted(relay: CloudRelay) -> bool:
    """Tell whether a relay should run: its robot has a ROS master and its Skill a cloud-capable component."""
    capable = getattr(relay, "cloud_capable", None)  # annotated by the reconciler's one query
    if capable is None:
        capable = relay.skill.components.filter(location__in=CLOUD_LOCATIONS).exists()
    return bool(relay.skill.robot.ros_master) and capable


def _free_port() -> int:
    """Pick a port nothing listens on and no other relay holds (the kernel's choice of a free one)."""
    taken = set(CloudRelay.objects.values_list("port", flat=True))
    for _ in range(20):
        with socket.socket() as probe:
            probe.bind(("0.0.0.0", 0))
            port = int(probe.getsockname()[1])
        if port not in taken:
            return port
    raise LaunchFailed("no free port for a cloud relay")


def _row(robot_id: str, skill_id: str) -> CloudRelay | None:
    return (
        CloudRelay.objects.select_related("skill__robot")
        .filter(skill__robot_id=robot_id, skill__skill_id=skill_id)
        .first()
    )


def converge_relay(robot_id: str, skill_id: str) -> str:
    """Run a Skill's relay while it is wanted; stop it once it is not (or its row is gone)."""

    def find() -> Service:
        relay = _row(robot_id, skill_id)
        return Service(
            name=f"the cloud relay of {robot_id}/{skill_id}" + (f" on port {relay.port}" if relay else ""),
            wanted=relay is not None and wanted(relay),
            start=lambda runtime: _start(runtime, relay),
            stop=lambda runtime: _stop(runtime, skill_id),
            ready=lambda timeout: relay is not None and tcp_answers(relay.port, timeout),
            report=lambda status, message: _set_status(relay, status, message) if relay is not None else None,
            runtime="process",
        )

    return converge(robot_id, f"relay:{robot_id}/{skill_id}", find)


async def _start(runtime: CloudRuntime, relay: CloudRelay) -> ComponentState:
    """Launch the relay process unless it runs already (whoever launched it)."""
    assert isinstance(runtime, CloudProcessRuntime)
    skill = relay.skill
    config = runtime.data_dir / f"relay-{skill.skill_id}.json"
    text = json.dumps(skill.config, sort_keys=True)
    found = await runtime._find(KIND_CLOUD_RELAY, skill.skill_id, RELAY_COMPONENT)
    if found is not None:
        if config.is_file() and config.read_text() == text:
            return ComponentState(
                skill=skill.skill_id, component=RELAY_COMPONENT, status=Status.RUNNING, pid_or_container_id=found.pid
            )
        await _stop(runtime, skill.skill_id)  # it routes an older config of the Skill
    runtime.data_dir.mkdir(parents=True, exist_ok=True)
    config.write_text(text)
    host = settings.BRIDGEOS["CLOUD_HOST"]
    command = [sys.executable, "-m", "bridgeos_agent.router.cloudrelay", "--config", str(config)]
    command += ["--master", skill.robot.ros_master, "--host", host, "--port", str(relay.port)]
    command += ["--robot", skill.robot_id]
    env = {"BRIDGEOS_CLOUD_RELAY_TOKEN": relay_token(skill.robot_id, skill.skill_id, relay)}
    if os.environ.get("PYTHONPATH"):
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]  # the worker's own agent package
    spec = _marked(
        runtime_spec(skill.robot_id, skill.skill_id, command, env),
        _key(KIND_CLOUD_RELAY, skill.robot_id, skill.skill_id, RELAY_COMPONENT),
    )
    return await ProcessRuntime.start(runtime, spec)


def runtime_spec(robot_id: str, skill_id: str, command: list[str], env: dict[str, str]) -> ComponentSpec:
    """Return the process spec of a relay (no restarts of its own: the reconciler restarts it)."""
    return ComponentSpec(
        robot=robot_id,
        skill=skill_id,
        component=RELAY_COMPONENT,
        location="cloud",
        launch=LaunchSpec(command=command),
        resources=ComponentResources(),
        env=env,
        restart=NO_RESTARTS,
    )


async def _stop(runtime: CloudRuntime, skill_id: str) -> None:
    assert isinstance(runtime, CloudProcessRuntime)
    await runtime._terminate_found(KIND_CLOUD_RELAY, skill_id, RELAY_COMPONENT, 10.0)


def _set_status(relay: CloudRelay, status: str, message: str = "") -> None:
    robot_id, skill_id = relay.skill.robot_id, relay.skill.skill_id
    report(
        relay,
        "status",
        status,
        message,
        robot_id=robot_id,
        text=f"Cloud relay of {robot_id}/{skill_id} on port {relay.port}",
        kind="cloud_relay",
        skill=skill_id,
        data={"port": relay.port, "status": status},
    )


# --------------------------------------------------------------------------- the reconciler


def observe_relays() -> list[Observed]:
    """List the relay processes of this cloud, for every robot."""

    async def scan(runtime: CloudRuntime) -> list[Observed]:
        return [item for item in await runtime.observe() if item.kind == KIND_CLOUD_RELAY]

    return with_runtime("reconciler", scan, name="process")


def reconcile_relays() -> int:
    """Start the wanted relays that are not running (crashed); stop those not wanted; return how many were fixed."""
    fixed = 0
    running = {(item.robot, item.skill): item for item in observe_relays()}
    capable = Component.objects.filter(skill=OuterRef("skill"), location__in=CLOUD_LOCATIONS)
    relays = CloudRelay.objects.select_related("skill__robot").annotate(cloud_capable=Exists(capable))
    rows = {(r.skill.robot_id, r.skill.skill_id): r for r in relays}
    for key, relay in rows.items():
        if relay.status == CS.FAILED and key not in running:
            continue  # it could not start: the next login (or a new row) tries again
        if wanted(relay) != (key in running):
            try:
                converge_relay(*key)
                fixed += 1
            except TryAgain as exc:
                logger.info("cloud relay of %s/%s: %s", *key, exc)
    for key, item in running.items():
        if key not in rows:
            try:
                with_runtime(item.robot, lambda runtime, item=item: runtime.remove(item), name="process")
                fixed += 1
            except RuntimeFailure as exc:
                logger.info("orphan cloud relay of %s/%s not removed now: %s", *key, exc)
    return fixed


def remove_relay_processes() -> int:
    """Stop every relay process of this cloud, touching no row; return how many there were."""
    found = observe_relays()
    for item in found:
        with_runtime(item.robot, lambda runtime, item=item: runtime.remove(item), name="process")
    return len(found)


def stop_all_relays() -> int:
    """Stop every relay process of this cloud and mark every relay stopped (cloud_down); return how many ran."""
    removed = remove_relay_processes()
    CloudRelay.objects.exclude(status=CS.STOPPED).update(status=CS.STOPPED)
    return removed
