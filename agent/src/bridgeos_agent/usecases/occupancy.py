"""Autonomous Mapping's map: a log-odds occupancy grid built from laser scans at known poses."""

from __future__ import annotations

import collections
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from bridgeos_agent.usecases.motion import Pose
from bridgeos_agent.usecases.world import Grid

__all__ = ["LogOddsMap", "ScanPairing", "map_agreement", "to_occupancy_values"]

Scan = TypeVar("Scan")


@dataclass
class LogOddsMap:
    """Accumulate evidence per cell: free along each beam, occupied where it ends on something."""

    grid: Grid
    hit: float = 0.85  # log-odds added to a cell a beam ends in
    miss: float = -0.4  # log-odds added to a cell a beam crosses
    limit: float = 6.0  # clamp, so the map can still change its mind

    def __post_init__(self) -> None:
        self.logodds = np.zeros((self.grid.height, self.grid.width), dtype=np.float32)
        self.scans = 0

    def integrate(self, pose: Pose, angles: np.ndarray, ranges: np.ndarray, max_range: float) -> None:
        """Fold one scan taken at a pose into the map."""
        ranges = np.asarray(ranges, dtype=np.float64)
        angles = np.asarray(angles, dtype=np.float64)
        valid = ~np.isnan(ranges)
        hits = valid & (ranges < max_range)
        reach = np.where(hits, ranges, max_range)[valid]
        beam = angles[valid] + pose.theta
        step = self.grid.resolution / 2.0
        steps = np.arange(0.0, max_range, step)
        # Cells a beam crosses, stopping half a cell short of where it ends.
        along = steps[None, :] < (reach[:, None] - step)
        xs = pose.x + np.cos(beam)[:, None] * steps[None, :]
        ys = pose.y + np.sin(beam)[:, None] * steps[None, :]
        iy, ix = self.grid.cell(xs[along], ys[along])
        free = self._flat(iy, ix)
        end = ranges[hits]
        eb = angles[hits] + pose.theta
        iy, ix = self.grid.cell(pose.x + np.cos(eb) * end, pose.y + np.sin(eb) * end)
        occupied = self._flat(iy, ix)
        free = np.setdiff1d(free, occupied, assume_unique=True)
        flat = self.logodds.reshape(-1)
        flat[free] += self.miss
        flat[occupied] += self.hit
        np.clip(flat, -self.limit, self.limit, out=flat)
        self.scans += 1

    def _flat(self, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
        keep = self.grid.inside(iy, ix)
        return np.unique(iy[keep] * self.grid.width + ix[keep])

    def occupancy(self) -> np.ndarray:
        """Return the map as ROS occupancy values: -1 unknown, else 0-100 percent occupied."""
        return to_occupancy_values(self.logodds)


class ScanPairing(Generic[Scan]):
    """Pair each scan with the odometry pose of the same stamp, waiting a moment for it, and fold the pairs."""

    def __init__(
        self,
        fold: Callable[[Scan, Pose], None],
        max_waiting: int = 100,
        max_poses: int = 400,
        patience_ns: int = 2_000_000_000,
    ) -> None:
        self.fold = fold
        self.max_waiting, self.max_poses, self.patience_ns = max_waiting, max_poses, patience_ns
        self.poses: collections.OrderedDict[int, Pose] = collections.OrderedDict()
        self.waiting: collections.deque[tuple[int, Scan]] = collections.deque()
        self.unpaired = 0

    def scan(self, stamp_ns: int, scan: Scan) -> None:
        """Take a scan; it is folded once its pose is known."""
        self.waiting.append((stamp_ns, scan))
        while len(self.waiting) > self.max_waiting:
            self.waiting.popleft()
        self._drain()

    def pose(self, stamp_ns: int, pose: Pose) -> None:
        """Take the odometry pose at a stamp."""
        self.poses[stamp_ns] = pose
        while len(self.poses) > self.max_poses:
            self.poses.popitem(last=False)
        self._drain()

    def _drain(self) -> None:
        while self.waiting:
            stamp, scan = self.waiting[0]
            pose = self.poses.get(stamp)
            if pose is not None:
                self.waiting.popleft()
                self.fold(scan, pose)
            elif self.poses and next(reversed(self.poses)) > stamp + self.patience_ns:
                self.waiting.popleft()  # its odometry never came (lost): two seconds is long enough
                self.unpaired += 1
            else:
                break


def to_occupancy_values(logodds: np.ndarray) -> np.ndarray:
    """Convert log-odds to nav_msgs/OccupancyGrid values (-1 where nothing was observed)."""
    probability = 1.0 - 1.0 / (1.0 + np.exp(logodds.astype(np.float64)))
    values = np.round(probability * 100).astype(np.int8)
    values[logodds == 0] = -1
    return values


def map_agreement(values: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Compare a built map (occupancy values) with the true grid over the cells it observed.

    ``agreement`` is the share of observed cells classified like the truth; ``occupied_precision``
    the share of cells the map calls occupied that lie within one cell of a true obstacle;
    ``observed`` the share of the world's cells observed at all.
    """
    observed = values >= 0
    occupied = values > 50
    agree = (occupied == truth) & observed
    near = truth.copy()
    near[1:, :] |= truth[:-1, :]
    near[:-1, :] |= truth[1:, :]
    near[:, 1:] |= truth[:, :-1]
    near[:, :-1] |= truth[:, 1:]
    n_observed = int(observed.sum())
    n_occupied = int(occupied.sum())
    return {
        "agreement": float(agree.sum() / n_observed) if n_observed else 0.0,
        "occupied_precision": float((occupied & near).sum() / n_occupied) if n_occupied else 0.0,
        "observed": float(n_observed / truth.size),
    }
