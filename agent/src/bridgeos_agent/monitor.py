"""Measure the robot's resources, real (psutil) or simulated, and decide which values to report.

Reporting is event-driven with conditional periodic sends (thesis §2.3.2): a value is
sent when it changed significantly since it was last sent, and at least every
``max_interval`` seconds otherwise, so a steady robot costs almost nothing to monitor.

Robot metric names (the dashboard and the Skill Managers read these):
``cpu`` %, ``ram`` %, ``ram_used`` MiB, ``bandwidth`` Mbit/s in+out, ``net_rx``/``net_tx``
bytes/s, ``net_cloud_rx``/``net_cloud_tx`` bytes/s exchanged with the cloud,
``io_read``/``io_write`` bytes/s, ``battery`` %, ``bandwidth_available`` Mbit/s, and per
network interface ``net_rx:IFACE``/``net_tx:IFACE`` bytes/s (loopback left out).
Per component (with ``skill`` and ``component``): ``cpu`` % of one core, ``ram`` MiB.
"""

from __future__ import annotations

import asyncio
import math
import random
import re
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import psutil

__all__ = ["RESOURCES", "Reporter", "ResourceMonitor", "Sample", "SimulatedRobot", "SystemRobot"]

RESOURCES = ("cpu", "gpu", "ram", "bandwidth", "io")  # what a robot config and allocation count
# Interface names that fit a metric name (veth pairs such as "veth1@if5" are left out).
_NIC = re.compile(r"[A-Za-z0-9_.:-]{1,64}")


@dataclass(frozen=True, slots=True)
class Sample:
    """One reading of the robot: metric values, and free resources in allocation units."""

    values: dict[str, float]
    free: dict[str, float]


@dataclass(slots=True)
class SimulatedRobot:
    """Synthetic resources so one machine can host many robots (``--simulate``).

    Load follows what runs on it (the components' declared needs) plus noise; bandwidth
    swings between ``bandwidth_min`` and the declared bandwidth with period ``period``;
    the battery drains faster under load.
    """

    cpu: float = 2.0
    ram: float = 2048.0
    bandwidth: float = 100.0
    io: float = 100.0
    gpu: int = 0
    bandwidth_min: float = 5.0
    period: float = 120.0
    battery_wh: float = 50.0
    seed: int | None = None
    _random: random.Random = field(init=False)
    _battery: float = field(init=False, default=100.0)
    _last: float | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self._random = random.Random(self.seed)

    def bandwidth_now(self, now: float) -> float:
        """Return the bandwidth available at ``now`` (Mbit/s)."""
        swing = (1 + math.sin(2 * math.pi * now / self.period)) / 2
        # The robot config sets the peak (apply_config): a low point above it would swing above the peak.
        low = min(self.bandwidth_min, self.bandwidth)
        return low + (self.bandwidth - low) * swing

    def sample(self, now: float, used: Mapping[str, float], cloud_bytes: tuple[float, float]) -> Sample:
        """Return a reading given the resources the running components use."""
        noise = self._random.uniform(-0.02, 0.02)
        cpu_used = min(self.cpu, used.get("cpu", 0.0) + 0.05 * self.cpu)
        ram_used = min(self.ram, used.get("ram", 0.0) + 0.1 * self.ram)
        cpu_pct = max(0.0, min(100.0, 100 * cpu_used / self.cpu + 100 * noise)) if self.cpu else 0.0
        available_bw = self.bandwidth_now(now)
        bw_used = min(available_bw, used.get("bandwidth", 0.0))
        if self._last is not None:
            hours = (now - self._last) / 3600
            watts = 5 + 20 * cpu_pct / 100
            self._battery = max(0.0, self._battery - 100 * watts * hours / self.battery_wh)
        self._last = now
        values = {
            "cpu": round(cpu_pct, 2),
            "ram": round(100 * ram_used / self.ram, 2) if self.ram else 0.0,
            "ram_used": round(ram_used, 1),
            "bandwidth": round(bw_used, 3),
            "bandwidth_available": round(available_bw, 3),
            "net_rx": round(bw_used * 1e6 / 16, 1),
            "net_tx": round(bw_used * 1e6 / 16, 1),
            "net_cloud_rx": round(cloud_bytes[0], 1),
            "net_cloud_tx": round(cloud_bytes[1], 1),
            "io_read": 0.0,
            "io_write": 0.0,
            "battery": round(self._battery, 2),
        }
        free = {
            "cpu": max(0.0, self.cpu - cpu_used),
            "gpu": float(self.gpu) - used.get("gpu", 0.0),
            "ram": max(0.0, self.ram - ram_used),
            "bandwidth": max(0.0, available_bw - bw_used),
            "io": max(0.0, self.io - used.get("io", 0.0)),
        }
        return Sample(values, free)


@dataclass(slots=True)
class SystemRobot:
    """Read the real machine with psutil; capacity comes from the robot config."""

    cpu: float = 2.0
    ram: float = 2048.0
    bandwidth: float = 100.0
    io: float = 100.0
    gpu: int = 0
    _net: tuple[float, int, int] | None = field(init=False, default=None)
    _nics: dict[str, tuple[float, int, int]] = field(init=False, default_factory=dict)
    _disk: tuple[float, int, int] | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        psutil.cpu_percent(None)  # the first call only starts the measurement window

    def sample(self, now: float, used: Mapping[str, float], cloud_bytes: tuple[float, float]) -> Sample:
        """Return a reading of the machine; ``used`` is what the running components reserved."""
        cpu_pct = psutil.cpu_percent(None)
        memory = psutil.virtual_memory()
        # Loopback is not the robot's network: leave it out of the totals.
        nics = {nic: c for nic, c in psutil.net_io_counters(pernic=True).items() if nic != "lo"}
        received = sum(c.bytes_recv for c in nics.values())
        sent = sum(c.bytes_sent for c in nics.values())
        rx_rate, tx_rate = self._rates("_net", now, received, sent)
        try:
            disk = psutil.disk_io_counters()
            read_rate, write_rate = self._rates("_disk", now, disk.read_bytes, disk.write_bytes) if disk else (0, 0)
        except (OSError, RuntimeError):  # no disk counters in some containers
            read_rate = write_rate = 0.0
        bandwidth_used = 8 * (rx_rate + tx_rate) / 1e6
        values = {
            "cpu": cpu_pct,
            "ram": memory.percent,
            "ram_used": round((memory.total - memory.available) / 2**20, 1),
            "bandwidth": round(bandwidth_used, 3),
            "bandwidth_available": round(max(0.0, self.bandwidth - bandwidth_used), 3),
            "net_rx": round(rx_rate, 1),
            "net_tx": round(tx_rate, 1),
            "net_cloud_rx": round(cloud_bytes[0], 1),
            "net_cloud_tx": round(cloud_bytes[1], 1),
            "io_read": round(read_rate, 1),
            "io_write": round(write_rate, 1),
        }
        for nic, counters in nics.items():
            # Containers' veth ends mirror their bridge; per-container traffic is the runtime's.
            if nic.startswith("veth") or not _NIC.fullmatch(nic):
                continue
            last = self._nics.get(nic)
            self._nics[nic] = (now, counters.bytes_recv, counters.bytes_sent)
            if last is not None and now > last[0]:
                span = now - last[0]
                values[f"net_rx:{nic}"] = round(max(0, counters.bytes_recv - last[1]) / span, 1)
                values[f"net_tx:{nic}"] = round(max(0, counters.bytes_sent - last[2]) / span, 1)
        battery = _battery_percent()
        if battery is not None:
            values["battery"] = battery
        # Free = the lesser of what is unreserved and what is measured idle.
        cores = psutil.cpu_count() or 1
        free = {
            "cpu": max(0.0, min(self.cpu - used.get("cpu", 0.0), cores * (1 - cpu_pct / 100))),
            "gpu": float(self.gpu) - used.get("gpu", 0.0),
            "ram": max(0.0, min(self.ram - used.get("ram", 0.0), memory.available / 2**20)),
            "bandwidth": max(0.0, min(self.bandwidth - used.get("bandwidth", 0.0), self.bandwidth - bandwidth_used)),
            "io": max(0.0, self.io - used.get("io", 0.0)),
        }
        return Sample(values, free)

    def _rates(self, slot: str, now: float, received: int, sent: int) -> tuple[float, float]:
        last = getattr(self, slot)
        setattr(self, slot, (now, received, sent))
        if last is None or now <= last[0]:
            return 0.0, 0.0
        span = now - last[0]
        return max(0, received - last[1]) / span, max(0, sent - last[2]) / span


def _battery_percent() -> float | None:
    sensors = getattr(psutil, "sensors_battery", None)
    try:
        battery = sensors() if sensors else None
    except (OSError, RuntimeError):
        return None
    return round(battery.percent, 2) if battery else None


class ResourceMonitor:
    """Sample a robot (real or simulated) and keep the latest reading."""

    def __init__(self, robot: SimulatedRobot | SystemRobot) -> None:
        self.robot = robot
        self.latest: Sample | None = None
        self._sampled: asyncio.Event | None = None  # set by the next reading (see next_sample)

    def sample(self, used: Mapping[str, float], cloud_bytes: tuple[float, float] = (0.0, 0.0)) -> Sample:
        """Take a reading now."""
        self.latest = self.robot.sample(time.time(), used, cloud_bytes)
        if self._sampled is not None:
            self._sampled.set()
            self._sampled = None
        return self.latest

    async def next_sample(self, timeout: float) -> bool:
        """Wait for the next reading; False if none came within ``timeout`` seconds."""
        if self._sampled is None:
            self._sampled = asyncio.Event()
        try:
            async with asyncio.timeout(timeout):
                await self._sampled.wait()
        except TimeoutError:
            return False
        return True

    def free(self, used: Mapping[str, float]) -> dict[str, float]:
        """Return the resources free for a new component now."""
        return self.sample(used).free


SeriesKey = tuple[str, str | None, str | None]


class Reporter:
    """Decide which values are worth sending: changed enough, or not sent for a while."""

    def __init__(self, *, max_interval: float = 10.0, relative: float = 0.05, absolute: float = 0.5) -> None:
        self.max_interval = max_interval
        self.relative = relative
        self.absolute = absolute
        self._sent: dict[SeriesKey, tuple[float, float]] = {}

    def select(
        self, now: float, values: Iterable[tuple[str, float, str | None, str | None]]
    ) -> list[dict[str, object]]:
        """Return the metric points to send out of (name, value, skill, component) readings."""
        points: list[dict[str, object]] = []
        sent = self._sent
        for name, value, skill, component in values:
            key = (name, skill, component)
            last = sent.get(key)
            if last is not None:
                last_value, last_at = last
                changed = abs(value - last_value) >= max(self.absolute, self.relative * abs(last_value))
                if not changed and now - last_at < self.max_interval:
                    continue
            sent[key] = (value, now)
            point: dict[str, object] = {"name": name, "value": value, "ts": now}
            if skill is not None:
                point["skill"] = skill
            if component is not None:
                point["component"] = component
            points.append(point)
        return points

    def forget(self, skill: str, component: str | None = None) -> None:
        """Drop the series of a stopped skill or component so a restart reports afresh."""
        for key in [k for k in self._sent if k[1] == skill and (component is None or k[2] == component)]:
            del self._sent[key]
