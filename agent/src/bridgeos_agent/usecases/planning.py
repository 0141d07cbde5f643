"""Path planning for Autonomous Navigation: A* on an inflated occupancy grid, then shortcuts."""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass

import numpy as np

from bridgeos_agent.usecases.world import Grid, disk_offsets, inflate

__all__ = ["GoalPlanner", "Plan", "astar", "plan_path", "segment_free"]

SQRT2 = math.sqrt(2.0)
NEIGHBOURS = [(-1, -1, SQRT2), (-1, 0, 1.0), (-1, 1, SQRT2), (0, -1, 1.0), (0, 1, 1.0), (1, -1, SQRT2), (1, 0, 1.0)]
NEIGHBOURS.append((1, 1, SQRT2))


def astar(blocked: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """Return the shortest 8-connected cell path from start to goal (both (iy, ix)), or None."""
    height, width = blocked.shape
    if blocked[goal] or blocked[start]:
        return None

    def h(cell: tuple[int, int]) -> float:  # octile distance: exact on an empty 8-connected grid
        dy, dx = abs(cell[0] - goal[0]), abs(cell[1] - goal[1])
        return (dx + dy) + (SQRT2 - 2.0) * min(dx, dy)

    best = {start: 0.0}
    parent: dict[tuple[int, int], tuple[int, int]] = {}
    frontier = [(h(start), 0.0, start)]
    while frontier:
        _, cost, cell = heapq.heappop(frontier)
        if cell == goal:
            path = [cell]
            while cell in parent:
                cell = parent[cell]
                path.append(cell)
            return path[::-1]
        if cost > best[cell]:
            continue  # a stale entry: the cell was reached more cheaply since
        cy, cx = cell
        for dy, dx, step in NEIGHBOURS:
            ny, nx = cy + dy, cx + dx
            if not (0 <= ny < height and 0 <= nx < width) or blocked[ny, nx]:
                continue
            # No corner cutting: a diagonal move needs both side cells free.
            if dy and dx and (blocked[cy, nx] or blocked[ny, cx]):
                continue
            new = cost + step
            if new < best.get((ny, nx), math.inf):
                best[(ny, nx)] = new
                parent[(ny, nx)] = cell
                heapq.heappush(frontier, (new + h((ny, nx)), new, (ny, nx)))
    return None


def segment_free(blocked: np.ndarray, grid: Grid, a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Say whether the straight segment a-b crosses no blocked cell (sampled finer than a cell)."""
    n = max(2, int(math.dist(a, b) / (grid.resolution / 4.0)) + 2)
    t = np.linspace(0.0, 1.0, n)
    iy, ix = grid.cell(a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t)
    if not grid.inside(iy, ix).all():
        return False
    return not blocked[iy, ix].any()


def plan_path(
    occupied: np.ndarray,
    grid: Grid,
    start: tuple[float, float],
    goal: tuple[float, float],
    robot_radius: float = 0.25,
) -> list[tuple[float, float]] | None:
    """Return a collision-free polyline from start to goal for a round robot, or None if none exists."""
    blocked = inflate(occupied, robot_radius / grid.resolution)
    (sy,), (sx,) = grid.cell([start[0]], [start[1]])
    (gy,), (gx,) = grid.cell([goal[0]], [goal[1]])
    s, g = (int(sy), int(sx)), (int(gy), int(gx))
    if not (grid.inside(np.array(s[0]), np.array(s[1])) and grid.inside(np.array(g[0]), np.array(g[1]))):
        return None
    if blocked[s] and not occupied[s]:
        # A robot pressed against a wall starts inside the inflation: free its own disk so it can leave.
        dy, dx = disk_offsets(robot_radius / grid.resolution)
        iy, ix = dy + s[0], dx + s[1]
        keep = grid.inside(iy, ix)
        blocked[iy[keep], ix[keep]] = occupied[iy[keep], ix[keep]]
    cells = astar(blocked, s, g)
    if cells is None:
        return None
    xs, ys = grid.center(np.array([c[0] for c in cells]), np.array([c[1] for c in cells]))
    points = [start, *zip(xs.tolist()[1:-1], ys.tolist()[1:-1], strict=True), goal]
    # String pulling: from each kept point jump to the farthest point still in plain sight.
    smooth = [points[0]]
    i = 0
    while i < len(points) - 1:
        j = len(points) - 1
        while j > i + 1 and not segment_free(blocked, grid, points[i], points[j]):
            j -= 1
        smooth.append(points[j])
        i = j
    return [(float(x), float(y)) for x, y in smooth]


@dataclass(frozen=True)
class Plan:
    """A plan for one goal: its points (None: no way there), whether it is new, and how long it took."""

    key: int
    points: list[tuple[float, float]] | None
    fresh: bool
    elapsed_ms: float = 0.0


@dataclass
class GoalPlanner:
    """Plan from the latest pose to the latest goal on the latest map, once per goal (a goal's key)."""

    robot_radius: float = 0.25
    blocked: np.ndarray | None = None
    grid: Grid | None = None
    position: tuple[float, float] | None = None
    goal: tuple[int, tuple[float, float]] | None = None
    planned: Plan | None = None

    def set_map(self, values: np.ndarray, grid: Grid) -> None:
        """Take a map's occupancy values (anything not free, unknown included, is an obstacle)."""
        self.blocked, self.grid = values != 0, grid

    def set_position(self, x: float, y: float) -> bool:
        """Take the robot's position; say whether a goal waits for its first plan."""
        self.position = (x, y)
        return self.goal is not None and (self.planned is None or self.planned.key != self.goal[0])

    def set_goal(self, key: int, x: float, y: float) -> None:
        """Take a goal; the same key again means the same goal sent again."""
        self.goal = (key, (x, y))

    def plan(self) -> Plan | None:
        """Return the current goal's plan (computed once per key), or None while map, pose or goal is missing."""
        if self.goal is None or self.position is None or self.blocked is None or self.grid is None:
            return None
        key, target = self.goal
        if self.planned is not None and self.planned.key == key:
            return Plan(key, self.planned.points, fresh=False)
        begin = time.perf_counter()
        points = plan_path(self.blocked, self.grid, self.position, target, self.robot_radius)
        self.planned = Plan(key, points, fresh=True, elapsed_ms=(time.perf_counter() - begin) * 1000)
        return self.planned
