"""The simulated robot's world: an occupancy grid made of rectangles, and a laser that sees it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["WORLDS", "Grid", "World", "cast_rays", "disk_offsets", "get_world", "inflate"]


@dataclass(frozen=True)
class Grid:
    """Place a 2-D cell array in the plane: cell (iy, ix) covers origin + (ix, iy) * resolution."""

    resolution: float
    origin_x: float
    origin_y: float
    width: int  # cells along x
    height: int  # cells along y

    def cell(self, x: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return the (iy, ix) cell indices of points, unclipped."""
        ix = np.floor((np.asarray(x) - self.origin_x) / self.resolution).astype(np.int64)
        iy = np.floor((np.asarray(y) - self.origin_y) / self.resolution).astype(np.int64)
        return iy, ix

    def inside(self, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
        """Return which cell indices fall inside the grid."""
        return (ix >= 0) & (ix < self.width) & (iy >= 0) & (iy < self.height)

    def center(self, iy: np.ndarray | int, ix: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Return the plane coordinates of cell centres."""
        x = self.origin_x + (np.asarray(ix) + 0.5) * self.resolution
        y = self.origin_y + (np.asarray(iy) + 0.5) * self.resolution
        return x, y


@dataclass(frozen=True)
class World:
    """A rectangular room with walls and boxes (x0, y0, x1, y1 in metres) on a grid."""

    name: str
    size_x: float
    size_y: float
    obstacles: tuple[tuple[float, float, float, float], ...]
    start: tuple[float, float, float]  # x, y, heading where the robot starts
    route: tuple[tuple[float, float], ...]  # the mapping tour's predefined waypoints
    goals: tuple[tuple[float, float], ...]  # the navigation tour's goals
    wall: float = 0.2

    def grid(self, resolution: float = 0.1) -> Grid:
        """Return the grid geometry at a resolution."""
        return Grid(resolution, 0.0, 0.0, round(self.size_x / resolution), round(self.size_y / resolution))

    def occupancy(self, resolution: float = 0.1) -> np.ndarray:
        """Rasterise the world: True where a cell is (even partly) covered by a wall or box."""
        grid = self.grid(resolution)
        occupied = np.zeros((grid.height, grid.width), dtype=bool)
        w = self.wall
        rects = [
            (0.0, 0.0, self.size_x, w),
            (0.0, self.size_y - w, self.size_x, self.size_y),
            (0.0, 0.0, w, self.size_y),
            (self.size_x - w, 0.0, self.size_x, self.size_y),
            *self.obstacles,
        ]
        eps = 1e-9
        for x0, y0, x1, y1 in rects:
            ix0 = max(0, math.floor(x0 / resolution + eps))
            ix1 = min(grid.width, math.ceil(x1 / resolution - eps))
            iy0 = max(0, math.floor(y0 / resolution + eps))
            iy1 = min(grid.height, math.ceil(y1 / resolution - eps))
            occupied[iy0:iy1, ix0:ix1] = True
        return occupied


# A 12 m x 8 m office: two partition walls and three boxes (a Husky-sized robot fits everywhere).
OFFICE = World(
    name="office",
    size_x=12.0,
    size_y=8.0,
    obstacles=(
        (4.0, 0.0, 4.2, 5.0),  # partition, open above y = 5
        (8.0, 3.0, 8.2, 8.0),  # partition, open below y = 3
        (1.5, 5.5, 2.5, 6.5),  # boxes
        (6.0, 1.0, 7.0, 2.0),
        (9.5, 0.8, 10.5, 1.6),
    ),
    start=(1.0, 1.0, 0.0),
    route=((1.0, 1.0), (3.0, 1.0), (3.0, 7.0), (6.0, 7.0), (6.0, 2.5), (11.0, 2.5), (11.0, 7.0), (9.0, 7.0)),
    goals=((3.0, 6.8), (6.5, 3.0), (10.8, 6.5), (1.0, 1.0)),
)

# A 6 m x 4 m room with one box: small and quick, for tests.
ROOM = World(
    name="room",
    size_x=6.0,
    size_y=4.0,
    obstacles=((2.6, 0.0, 3.0, 2.6),),
    start=(1.0, 1.0, 0.0),
    route=((1.0, 1.0), (1.0, 3.2), (4.5, 3.2), (4.5, 1.0)),
    goals=((4.5, 1.0),),
)

WORLDS = {world.name: world for world in (OFFICE, ROOM)}


def get_world(name: str) -> World:
    """Return a world by name, or raise ValueError naming the known ones."""
    try:
        return WORLDS[name]
    except KeyError:
        raise ValueError(f"unknown world {name!r} (known: {', '.join(sorted(WORLDS))})") from None


def disk_offsets(radius_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the (dy, dx) cell offsets within a disk."""
    r = math.ceil(radius_cells)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    keep = dx * dx + dy * dy <= radius_cells * radius_cells + 1e-9
    return dy[keep], dx[keep]


def inflate(occupied: np.ndarray, radius_cells: float) -> np.ndarray:
    """Grow obstacles by a radius in cells (so a robot's centre may go wherever is left free)."""
    out = occupied.copy()
    height, width = occupied.shape
    for dy, dx in zip(*disk_offsets(radius_cells), strict=True):
        src = occupied[max(0, -dy) : height - max(0, dy), max(0, -dx) : width - max(0, dx)]
        out[max(0, dy) : height - max(0, -dy), max(0, dx) : width - max(0, -dx)] |= src
    return out


def cast_rays(
    occupied: np.ndarray,
    grid: Grid,
    x: float,
    y: float,
    angles: np.ndarray,
    max_range: float,
) -> np.ndarray:
    """Return the range to the first occupied cell along each ray (inf where nothing within max_range)."""
    step = grid.resolution / 3.0
    steps = np.arange(1, int(max_range / step) + 1, dtype=np.float64) * step
    xs = x + np.cos(angles)[:, None] * steps[None, :]
    ys = y + np.sin(angles)[:, None] * steps[None, :]
    iy, ix = grid.cell(xs, ys)
    inside = grid.inside(iy, ix)
    hit = ~inside  # the world ends in a wall anyway; treat leaving it as a hit
    hit[inside] = occupied[iy[inside], ix[inside]]
    first = np.argmax(hit, axis=1)
    ranges = steps[first]
    ranges[~hit.any(axis=1)] = np.inf
    return ranges
