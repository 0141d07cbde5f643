"""Run the cloud's per-robot services (a ROS master, a ROS 2 discovery server, a Skill's relay) alike.

Each kind says what its service is (``Service``); ``converge`` runs it while it is wanted and stops
it once it is not, under one orchestration lock; ``report`` keeps its status and logs each change
as an event; the probes tell when its port is taken. The kinds differ only in what they start.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from django.conf import settings
from django.db import transaction
from django.db.models import Model
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.runtime.base import ComponentState, RuntimeFailure, Status
from monitoring.choices import Level
from monitoring.services import record_event
from robots.services import hold_robot

from .locks import LockBusy, orchestration_lock
from .orchestration import LaunchFailed, TryAgain, unreachable, with_runtime
from .runtime import CloudRuntime

__all__ = ["Service", "converge", "free_port_in", "report", "tcp_answers", "udp_bound", "udp_held"]

# How long a started service may take to take its port before the reconciler tries again.
READY_S = 15.0


@dataclass(frozen=True)
class Service:
    """One per-robot service as the reconciler found it: whether it should run, and how to run, check and report it."""

    name: str  # "the ROS master of r1 on port 11400", for messages
    wanted: bool
    start: Callable[[CloudRuntime], Awaitable[ComponentState]]
    stop: Callable[[CloudRuntime], Awaitable[Any]]
    ready: Callable[[float], bool]  # whether it holds its port within the seconds given
    report: Callable[[str, str], None]  # (status, message)
    runtime: str | None = None  # the cloud runtime it runs on (None: the robot's)


def converge(robot_id: str, lock: str, find: Callable[[], Service | str]) -> str:
    """Run a service while wanted and stop it once not; return running, stopped, failed or what ``find`` said.

    ``find`` is called under the lock and returns the service, or a word when there is nothing to do.
    A cloud runtime out of reach, a lock held elsewhere or a port not taken yet raise TryAgain.
    """
    try:
        with orchestration_lock(lock):
            service = find()
            if isinstance(service, str):
                return service
            try:
                if not service.wanted:
                    with_runtime(robot_id, service.stop, name=service.runtime)
                    service.report(CS.STOPPED, "")
                    return "stopped"
                state = with_runtime(robot_id, service.start, name=service.runtime)
            except (RuntimeFailure, LaunchFailed, OSError) as exc:
                if isinstance(exc, RuntimeFailure) and unreachable(exc):
                    raise TryAgain(str(exc)) from None
                service.report(CS.FAILED, str(exc))
                return "failed"
            if state.status is Status.RUNNING and service.ready(READY_S):
                service.report(CS.RUNNING, "")
                return "running"
            if state.status is Status.RUNNING:
                raise TryAgain(f"{service.name} runs but does not hold its port yet")
            service.report(CS.FAILED, state.message or f"exit code {state.exit_code}")
            return "failed"
    except LockBusy as exc:
        raise TryAgain(str(exc)) from None


def report(
    row: Model, field: str, status: str, message: str, *, robot_id: str, text: str, kind: str, **event: Any
) -> None:
    """Keep a service's status in ``row.<field>`` and its message; log each change as a cloud event."""
    if getattr(row, field) == status and getattr(row, "message", "") == message:
        return
    with transaction.atomic():
        if not hold_robot(robot_id):
            return  # deleted since its service was found: its rows and events are gone with it
        type(row)._default_manager.filter(pk=row.pk).update(
            **{field: status}, message=message, updated_at=timezone.now()
        )
        setattr(row, field, status)
        row.message = message  # type: ignore[attr-defined]
        record_event(
            f"{text} is {status}" + (f": {message}" if message else ""),
            robot_id=robot_id,
            level=Level.ERROR if status == CS.FAILED else Level.INFO,
            kind=kind,
            **event,
        )


def free_port_in(setting: str, taken: set[int], held: Callable[[int], bool], what: str) -> int:
    """Pick the lowest port of a configured range ("low-high") that no row holds and nothing uses."""
    low, _, high = settings.BRIDGEOS[setting].partition("-")
    for port in range(int(low), int(high or low) + 1):
        if port not in taken and not held(port):
            return port
    raise LaunchFailed(f"no free port for {what} in BRIDGEOS_{setting}={low}-{high}")


def tcp_bound(port: int) -> bool:
    """Tell whether a TCP socket of this host holds the port."""
    with socket.socket() as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return True
    return False


def udp_bound(port: int) -> bool:
    """Tell whether a UDP socket of this host holds the port (a discovery server listens on UDP only)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return True
    return False


def tcp_answers(port: int, timeout: float) -> bool:
    """Tell whether something accepts connections on the cloud host's port within ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((settings.BRIDGEOS["CLOUD_HOST"], port), timeout=1).close()
            return True
        except OSError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


def udp_held(port: int, timeout: float) -> bool:
    """Tell whether a service holds its UDP port within ``timeout`` (it has no TCP port to connect to)."""
    deadline = time.monotonic() + timeout
    while not udp_bound(port):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)
    return True
