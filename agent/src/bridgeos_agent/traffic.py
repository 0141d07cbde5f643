"""What a Skill Router measured of one component's traffic, as its Skill Manager reads it."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ComponentTraffic"]

GB = 1e9


@dataclass(frozen=True, slots=True)
class ComponentTraffic:
    """Count one component's routed messages over a window (the policies' BW and loss inputs)."""

    seconds: float = 0.0  # length of the window the counts cover
    bytes_robot: int = 0  # exchanged with peers that run on the robot
    bytes_cloud: int = 0  # exchanged with peers that run in the cloud
    messages: int = 0  # messages routed to or from the component
    dropped: int = 0  # of those, lost or dropped on the way

    @property
    def loss_rate(self) -> float:
        """Return the share of the component's messages that were lost (0-1)."""
        return self.dropped / self.messages if self.messages else 0.0

    def gb_per_hour(self) -> tuple[float, float]:
        """Return the traffic with robot-side and cloud-side peers in GB per hour."""
        if self.seconds <= 0:
            return 0.0, 0.0
        scale = 3600.0 / (self.seconds * GB)
        return self.bytes_robot * scale, self.bytes_cloud * scale
