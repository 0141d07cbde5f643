"""Say where a Skill Router listens and what it advertises, and where a component may run."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

__all__ = ["LOCATIONS", "RouterSettings", "Where", "locations", "router_settings_from_env"]

Where = Literal["robot", "cloud"]
LOCATIONS: tuple[Where, ...] = ("robot", "cloud")


@dataclass(kw_only=True)
class RouterSettings:
    """Where the router listens and what it advertises (from the environment by default)."""

    http_host: str = "0.0.0.0"
    http_advertise: str = "127.0.0.1"
    ros_host: str = "127.0.0.1"
    ready_timeout: float = 30.0
    statistics_period: float = 1.0
    drain_timeout: float = 10.0

    def __post_init__(self) -> None:
        for name in ("http_host", "http_advertise", "ros_host"):
            value = getattr(self, name)
            if not value or any(c.isspace() for c in value) or "/" in value:
                raise ValueError(f"router setting {name}: {value!r} is not a host name or address")
        for name in ("ready_timeout", "statistics_period", "drain_timeout"):
            seconds = getattr(self, name)
            if not (math.isfinite(seconds) and seconds > 0):
                raise ValueError(f"router setting {name}: must be a positive number of seconds, not {seconds!r}")


def router_settings_from_env(env: Mapping[str, str] | None = None) -> RouterSettings:
    """Read the router's settings: BRIDGEOS_ROUTER_HTTP_HOST/_ADVERTISE, ROS_IP or ROS_HOSTNAME, timeouts."""
    env = os.environ if env is None else env

    def seconds(name: str, default: float) -> float:
        raw = env.get(name)
        if raw is None or raw == "":
            return default
        try:
            return float(raw)
        except ValueError:
            raise ValueError(f"{name}: {raw!r} is not a number of seconds") from None

    http_host = env.get("BRIDGEOS_ROUTER_HTTP_HOST") or "0.0.0.0"
    default_advertise = "127.0.0.1" if http_host in ("0.0.0.0", "::") else http_host
    return RouterSettings(
        http_host=http_host,
        http_advertise=env.get("BRIDGEOS_ROUTER_HTTP_ADVERTISE") or default_advertise,
        ros_host=env.get("ROS_IP") or env.get("ROS_HOSTNAME") or "127.0.0.1",
        ready_timeout=seconds("BRIDGEOS_ROUTER_READY_TIMEOUT", 30.0),
        statistics_period=seconds("BRIDGEOS_ROUTER_STATISTICS_PERIOD", 1.0),
    )


def locations(where: str) -> tuple[Where, ...]:
    """Return the locations a component of ``location`` (robot, cloud or either) can run on."""
    if where == "either":
        return LOCATIONS
    return tuple(location for location in LOCATIONS if location == where)
