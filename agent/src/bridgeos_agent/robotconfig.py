"""Define and validate a robot's configuration: capacity, allocation and offloading."""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, field_validator, model_validator
from pydantic_core import PydanticCustomError

from bridgeos_agent.skillconfig import IDENTIFIER_PATTERN

__all__ = [
    "Costs",
    "Heuristic",
    "HeuristicWeights",
    "LogsPolicy",
    "Offloading",
    "RobotConfig",
    "RobotResources",
    "Subnets",
    "Vpn",
    "merge_config_changes",
    "parse_robot_config",
    "robot_config_json_schema",
]

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

Identifier = Annotated[str, StringConstraints(pattern=IDENTIFIER_PATTERN)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]

# The five heuristics of thesis section 3.3.1 that Algorithm 1 may use to rank replacements.
Heuristic = Literal[
    "resource_usage",  # Algorithm 2: geometric mean of wasted-resource ratios.
    "migration_cost",  # Algorithm 3: bytes (and money) to migrate the replacement's state.
    "resource_expenditure",  # Algorithm 4: weighs waste, migration cost and network loss.
    "temporal_cost",  # Algorithm 5: expected time to migrate given spare bandwidth.
    "weighted_cost",  # Algorithm 6: weighs expenditure against time.
]

# auto: Skill Managers decide adaptively (Algorithm 8's "dynamic" strategy).
# manual: only recommendations pushed by components or operators move components.
# robot: every 'either' component is kept on the robot while resources allow.
# cloud: every 'either' component is kept in the cloud.
Offloading = Literal["auto", "manual", "robot", "cloud"]

DEFAULT_ENERGY: dict[str, float] = {
    "cpu": 10.0,
    "gpu": 0.0,
    "ram": 2.0,
    "io": 1.5,
    "wifi": 2.5,
}


class _Model(BaseModel):
    """Reject unknown fields so typos surface as errors instead of silent defaults."""

    model_config = ConfigDict(extra="forbid")


class RobotResources(_Model):
    """Declare the robot's capacity that Algorithm 1 allocates components into."""

    cpu: NonNegative = Field(default=2.0, description="CPU cores.")
    gpu: int = Field(default=0, ge=0, le=64, description="GPUs.")
    ram: NonNegative = Field(default=2048.0, description="Memory in MiB.")
    bandwidth: NonNegative = Field(default=100.0, description="Network in Mbit/s.")
    io: NonNegative = Field(default=100.0, description="Disk I/O in MB/s.")
    battery: NonNegative | None = Field(
        default=None, description="Battery capacity in Wh; unset for a mains-powered robot."
    )


class HeuristicWeights(_Model):
    """Weigh the terms of the combined heuristics (Algorithms 4 and 6)."""

    gain: NonNegative = Field(default=1.0, description="Weight of avoided resource waste.")
    cost: NonNegative = Field(default=1.0, description="Weight of migration cost.")
    loss: NonNegative = Field(default=1.0, description="Weight of added network usage.")
    time: NonNegative = Field(default=1.0, description="Weight of migration time.")


class Subnets(_Model):
    """Name the robot's private subnetworks on the robot and in the cloud."""

    local: str = Field(description="CIDR of the robot's local container network.")
    cloud: str = Field(description="CIDR of the robot's cloud container network.")

    @field_validator("local", "cloud")
    @classmethod
    def _cidr(cls, value: str) -> str:
        """Accept only a network address in CIDR notation and normalise it."""
        try:
            return str(ipaddress.ip_network(value, strict=True))
        except ValueError as exc:
            raise ValueError(f"not a CIDR network: {exc}") from None

    @model_validator(mode="after")
    def _disjoint(self) -> Subnets:
        """Reject subnets that overlap, since routing between them would be ambiguous."""
        local = ipaddress.ip_network(self.local)
        cloud = ipaddress.ip_network(self.cloud)
        if local.version == cloud.version and local.overlaps(cloud):
            raise PydanticCustomError(
                "robot_config",
                "{summary}",
                {
                    "summary": f"cloud: overlaps the local subnet {self.local}",
                    "issues": ((("cloud",), f"overlaps the local subnet {self.local}"),),
                },
            )
        return self


class Vpn(_Model):
    """Say whether the robot joins the cloud's VPN, and where the cloud answers inside it."""

    enabled: bool = Field(default=False, description="Bring the OpenVPN tunnel up and reach the cloud through it.")
    master: str | None = Field(
        default=None,
        max_length=2048,
        pattern=r"^wss?://[^/?#\s]+/?$",
        description="The cloud's WebSocket URL inside the tunnel (set by the cloud), e.g. wss://10.8.0.1:8443.",
    )


class ImagePolicy(_Model):
    """Say how a robot keeps the images it pulls from the cloud's registry."""

    keep_per_repository: int = Field(
        default=3,
        ge=1,
        le=100,
        description="Pulled images kept per repository besides those a Skill uses (the newest first).",
    )
    disk_reserve_mb: NonNegative = Field(
        default=256, description="Disk (MiB) a pull must leave free under Docker's data root, else disk_full."
    )


class LogsPolicy(_Model):
    """Say how a robot keeps its components' output and ships it to the cloud."""

    enabled: bool = Field(
        default=True, description="Ship components' stdout and stderr to the cloud (off: kept in the robot's rings)."
    )
    ring_bytes: int = Field(
        default=8 * 1024 * 1024,
        ge=64 * 1024,
        le=1024 * 1024 * 1024,
        description="Bytes of each component's last lines kept on the robot's disk (its ring), shipped or not.",
    )
    rate_lines_per_s: int = Field(
        default=25_000, ge=1, le=1_000_000, description="Lines a second the robot ships at most (all components)."
    )
    rate_bytes_per_s: int = Field(
        default=4 * 1024 * 1024,
        ge=1024,
        le=1024 * 1024 * 1024,
        description="Bytes a second of log frames the robot ships at most; lines over either cap are dropped, counted.",
    )


class Costs(_Model):
    """Price the resources used by the monetary policy and migration heuristics."""

    per_gb: NonNegative = Field(default=0.1, description="Price of one GB exchanged (C_GB).")
    per_kwh: NonNegative = Field(default=0.25, description="Price of one kWh (C_KW).")
    cloud: dict[Identifier, NonNegative] = Field(
        default_factory=dict,
        description="Hourly price of each cloud resource at full use (C_r of eq. 4.6).",
    )


class RobotConfig(_Model):
    """Validate a robot's configuration; the defaults are a new robot's configuration."""

    model_config = ConfigDict(
        extra="forbid",
        title="bridgeOS Robot configuration",
        json_schema_extra={"$schema": JSON_SCHEMA_DIALECT},
    )

    resources: RobotResources = Field(default_factory=RobotResources)
    heuristic: Heuristic = Field(
        default="resource_usage",
        description="Heuristic Algorithm 1 uses to pick a component to move to the cloud.",
    )
    threshold: float = Field(
        default=0.5,
        allow_inf_nan=False,
        description="Highest heuristic cost at which a running component is replaced.",
    )
    weights: HeuristicWeights = Field(default_factory=HeuristicWeights)
    offloading: Offloading = Field(
        default="auto",
        description=(
            "auto: adaptive decisions; manual: recommendations only; "
            "robot: keep movable components on the robot; cloud: keep them in the cloud."
        ),
    )
    subnets: Subnets | None = None
    vpn: Vpn = Field(default_factory=Vpn)
    images: ImagePolicy = Field(default_factory=ImagePolicy)
    logs: LogsPolicy = Field(default_factory=LogsPolicy)
    tls_ca: str | None = Field(
        default=None,
        max_length=65536,
        pattern=r"^\s*-----BEGIN CERTIFICATE-----[\s\S]+-----END CERTIFICATE-----\s*$",
        description="PEM of the CA the agent pins for the cloud's TLS certificate (set by the cloud).",
    )
    energy: dict[Identifier, NonNegative] = Field(
        default_factory=lambda: dict(DEFAULT_ENERGY),
        description="Hourly energy consumption (Ec, watts) of each resource at full use.",
    )
    costs: Costs = Field(default_factory=Costs)
    heartbeat_interval: float = Field(
        default=5.0, gt=0, le=300, allow_inf_nan=False, description="Seconds between heartbeats."
    )
    connection_lost_after: float = Field(
        default=15.0,
        gt=0,
        le=3600,
        allow_inf_nan=False,
        description="Seconds of silence after which the cloud is deemed lost (takeover).",
    )

    @model_validator(mode="after")
    def _lost_after_heartbeat(self) -> RobotConfig:
        """Require the loss delay to outlast a heartbeat, or every gap would look like a loss."""
        if self.connection_lost_after <= self.heartbeat_interval:
            message = f"must be longer than heartbeat_interval ({self.heartbeat_interval:g} s)"
            raise PydanticCustomError(
                "robot_config",
                "{summary}",
                {
                    "summary": f"connection_lost_after: {message}",
                    "issues": ((("connection_lost_after",), message),),
                },
            )
        return self


def robot_config_json_schema() -> dict[str, Any]:
    """Return the JSON Schema of a robot configuration."""
    return RobotConfig.model_json_schema(mode="validation")


def parse_robot_config(data: dict[str, Any] | str | bytes) -> RobotConfig:
    """Parse and validate a robot configuration from a dict or JSON text."""
    if isinstance(data, str | bytes | bytearray):
        return RobotConfig.model_validate_json(data)
    return RobotConfig.model_validate(data)


def merge_config_changes(base: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """Apply a partial change (robot_config_update) to a config, recursing into nested objects."""
    merged = dict(base)
    for key, value in changes.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = merge_config_changes(merged[key], value)
        else:
            merged[key] = value
    return merged
