"""Everything ``bridgeos-agent run`` tells the Robot Controller, with the defaults the CLI starts from."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridgeos_agent.monitor import SimulatedRobot
from bridgeos_agent.outbox import DEFAULT_MEMORY_BYTES

__all__ = ["AgentSettings"]


@dataclass
class AgentSettings:
    """Everything `bridgeos-agent run` is told."""

    master: str
    robot: str
    token: str
    data_dir: Path
    # Where the token is kept (--token-file): a new token the cloud gives the robot replaces it there.
    token_file: Path | None = None
    runtime: str = "process"
    simulate: bool = False
    sample_interval: float = 1.0
    # Seconds between metrics frames; the samples taken meanwhile go in one frame (0: a frame per
    # sample). The cloud's cost is per frame, not per point: a large fleet reports every few seconds.
    report_interval: float = 0.0
    report_max_interval: float = 10.0
    startup_parallelism: int = 8
    outbox_max_bytes: int = 64 * 1024 * 1024
    outbox_memory_bytes: int = DEFAULT_MEMORY_BYTES  # metric frames kept in memory while the disk is full
    reconnect_initial: float = 1.0
    # Retries back off to at most 3 s, so every robot is back within ~5 s of the cloud's return
    # (issue 20); a refused connect to a cloud that is down costs it nothing.
    reconnect_max: float = 3.0
    runtime_options: dict[str, Any] = field(default_factory=dict)
    detect_ros_master: bool = True
    ros2: str = "auto"  # auto (when rclpy is importable and the robot is not simulated) | on | off
    stop_components_on_exit: bool = False
    simulated: SimulatedRobot | None = None
    # How long a move to the cloud waits for the cloud to report its copy running.
    cloud_start_timeout: float = 90.0
    # How often Skill volumes are scanned for changes to send to the cloud (0: never).
    volume_sync_interval: float = 1.0
    ca_file: Path | None = None  # the CA that signs the cloud's TLS certificate (else pinned, else the system's)
    allow_insecure: bool = False  # plain ws:// to another machine
    vpn_device: str = "bridgeos-vpn"
    openvpn: str = "openvpn"
    firewall: str = "auto"  # auto (apply when root, else print) | apply | print | off
    # Labels asked for at first registration (--label); the cloud ignores them once the robot has any.
    labels: dict[str, str] = field(default_factory=dict)
