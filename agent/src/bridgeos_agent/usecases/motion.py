"""Kinematics of the simulated differential-drive robot and the path follower that drives it."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Follower", "Pose", "WheelOdometry", "integrate", "wrap_angle"]


@dataclass(frozen=True)
class Pose:
    """A planar pose: position in metres, heading in radians."""

    x: float
    y: float
    theta: float


def wrap_angle(angle: float) -> float:
    """Return an angle in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def integrate(pose: Pose, v: float, w: float, dt: float) -> Pose:
    """Move a unicycle at linear speed v and turn rate w for dt seconds (exact arcs)."""
    if abs(w) < 1e-9:
        return Pose(pose.x + v * math.cos(pose.theta) * dt, pose.y + v * math.sin(pose.theta) * dt, pose.theta)
    theta = pose.theta + w * dt
    radius = v / w
    return Pose(
        pose.x + radius * (math.sin(theta) - math.sin(pose.theta)),
        pose.y - radius * (math.cos(theta) - math.cos(pose.theta)),
        wrap_angle(theta),
    )


@dataclass
class Follower:
    """Follow a polyline with pure pursuit: turn in place first when the target is far off the heading."""

    path: list[tuple[float, float]]
    max_speed: float = 0.5
    max_turn: float = 1.5
    lookahead: float = 0.4
    tolerance: float = 0.1
    index: int = 0  # the path point the robot has reached: progress never goes back

    @property
    def done(self) -> bool:
        """Say whether the end of the path is reached."""
        return not self.path or self.index >= len(self.path)

    def command(self, pose: Pose) -> tuple[float, float]:
        """Return the (v, w) that brings the robot along the path from its pose."""
        if self.done:
            return 0.0, 0.0
        last = len(self.path) - 1
        # Advance past every point already within the lookahead (the last one needs the tolerance).
        while self.index < last and math.dist((pose.x, pose.y), self.path[self.index]) < self.lookahead:
            self.index += 1
        target = self.path[self.index]
        distance = math.dist((pose.x, pose.y), target)
        if self.index == last and distance < self.tolerance:
            self.index = len(self.path)
            return 0.0, 0.0
        error = wrap_angle(math.atan2(target[1] - pose.y, target[0] - pose.x) - pose.theta)
        turn = max(-self.max_turn, min(self.max_turn, 2.5 * error))
        if abs(error) > math.radians(50):
            return 0.0, turn  # face the target before driving on
        speed = self.max_speed * math.cos(error)
        if self.index == last:
            speed = min(speed, max(0.1, distance))  # slow down onto the goal
        return speed, turn


@dataclass
class WheelOdometry:
    """Integrate wheel speeds, each for the step ending at its stamp, into a pose (a lost step is drift)."""

    pose: Pose
    stamp_ns: int | None = None

    def update(self, stamp_ns: int, v: float, w: float) -> Pose:
        """Account for the wheels having turned at (v, w) until stamp_ns; return the pose then."""
        if self.stamp_ns is not None:
            dt = (stamp_ns - self.stamp_ns) / 1e9
            if dt > 0:
                self.pose = integrate(self.pose, v, w, dt)
        self.stamp_ns = stamp_ns
        return self.pose
