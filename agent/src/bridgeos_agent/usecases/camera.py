"""The simulated RGB-D camera: ray-cast a room with people in it into an organised pointcloud.

Points are in the camera's body frame (x forward, y left, z up, origin at the lens, the floor
``height`` below it) and packed like PCL's PointXYZRGB: 32 bytes a point, so 1280 x 960
pixels make the thesis's ~40 MB cloud.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "POINT_DTYPE",
    "Box",
    "Person",
    "Scene",
    "default_scene",
    "parse_people",
    "render",
    "size_for_megabytes",
]

# PCL PointXYZRGB: x y z, 4 bytes of padding, rgb packed in a float, 12 bytes of padding.
POINT_DTYPE = np.dtype(
    {"names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<f4"], "offsets": [0, 4, 8, 16], "itemsize": 32}
)


@dataclass(frozen=True)
class Person:
    """A standing person as a vertical cylinder on the floor."""

    x: float
    y: float
    radius: float = 0.22
    height: float = 1.75


@dataclass(frozen=True)
class Box:
    """Furniture: an axis-aligned box standing on the floor."""

    x0: float
    y0: float
    x1: float
    y1: float
    height: float


@dataclass(frozen=True)
class Scene:
    """A room in front of the camera: floor, ceiling, three walls, furniture and people."""

    people: tuple[Person, ...]
    furniture: tuple[Box, ...] = field(default=())
    depth: float = 8.0  # back wall, metres ahead
    half_width: float = 4.0  # side walls, metres left and right
    camera_height: float = 1.0
    ceiling: float = 2.6


def default_scene(people: list[tuple[float, float]] | None = None) -> Scene:
    """Return the standard scene: three people, a table, a cabinet and a lamp pole."""
    spots = people if people is not None else [(3.0, 1.0), (4.5, -1.2), (6.0, 0.3)]
    return Scene(
        people=tuple(Person(x, y) for x, y in spots),
        furniture=(
            Box(5.0, 1.2, 5.8, 2.0, 0.75),  # a table: too low for a person
            Box(6.6, 2.2, 7.2, 3.8, 1.9),  # a cabinet: too wide
            Box(3.5, -0.3, 3.56, -0.24, 1.9),  # a lamp pole: too thin
        ),
    )


def parse_people(text: str) -> list[tuple[float, float]]:
    """Parse 'x,y;x,y' into people positions (an empty string is no people)."""
    spots = []
    for part in filter(None, (p.strip() for p in text.split(";"))):
        try:
            x, y = (float(v) for v in part.split(","))
        except ValueError:
            raise ValueError(f"a person is 'x,y' in metres, not {part!r}") from None
        if not (0.5 < x < 50 and abs(y) < 50):
            raise ValueError(f"person {part!r} is not in front of the camera")
        spots.append((x, y))
    return spots


def size_for_megabytes(megabytes: float) -> tuple[int, int]:
    """Return a 4:3 width and height whose cloud is about this many megabytes."""
    pixels = megabytes * 1e6 / POINT_DTYPE.itemsize
    width = max(4, round(math.sqrt(pixels * 4 / 3) / 4) * 4)
    return width, max(3, round(width * 3 / 4))


def _pack_rgb(r: int, g: int, b: int) -> float:
    return float(np.array([(r << 16) | (g << 8) | b], dtype="<u4").view("<f4")[0])


def render(scene: Scene, width: int, height: int, hfov_deg: float = 58.0, seed: int = 0) -> np.ndarray:
    """Ray-cast the scene into an organised cloud (height x width points; NaN where nothing is hit)."""
    focal = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    u = (np.arange(width, dtype=np.float64) - (width - 1) / 2) / focal
    v = (np.arange(height, dtype=np.float64) - (height - 1) / 2) / focal
    dy = np.broadcast_to(-u[None, :], (height, width)).reshape(-1)
    dz = np.broadcast_to(-v[:, None], (height, width)).reshape(-1)
    dx = np.ones_like(dy)
    n = dx.size
    t = np.full(n, np.inf)
    color = np.zeros(n, dtype=np.float32)
    floor_z = -scene.camera_height
    top_z = scene.ceiling - scene.camera_height

    def take(candidate: np.ndarray, rgb: float | np.ndarray) -> None:
        closer = (candidate > 1e-6) & (candidate < t)
        t[closer] = candidate[closer]
        color[closer] = rgb[closer] if isinstance(rgb, np.ndarray) else rgb

    with np.errstate(divide="ignore", invalid="ignore"):
        take(np.where(dz < 0, floor_z / dz, np.inf), _pack_rgb(120, 110, 100))
        take(np.where(dz > 0, top_z / dz, np.inf), _pack_rgb(240, 240, 240))
        take(scene.depth / dx, _pack_rgb(200, 200, 180))
        take(np.where(dy > 0, scene.half_width / dy, np.inf), _pack_rgb(190, 200, 210))
        take(np.where(dy < 0, -scene.half_width / dy, np.inf), _pack_rgb(190, 200, 210))
        for box in scene.furniture:
            take(_box_hits(box, dx, dy, dz, floor_z), _pack_rgb(140, 90, 40))
        shirts = [(200, 40, 40), (40, 90, 200), (40, 160, 60), (220, 180, 40)]
        for index, person in enumerate(scene.people):
            take(_cylinder_hits(person, dx, dy, dz, floor_z), _pack_rgb(*shirts[index % len(shirts)]))
    # Depth noise grows with the square of the distance, as structured-light sensors' does.
    rng = np.random.default_rng(seed)
    finite = np.isfinite(t)
    t[finite] += rng.normal(0.0, 1.0, int(finite.sum())) * 0.0015 * t[finite] ** 2
    points = np.zeros(n, dtype=POINT_DTYPE)
    for name, d in (("x", dx), ("y", dy), ("z", dz)):
        points[name] = np.where(finite, t * d, np.nan)
    points["rgb"] = color
    return points.reshape(height, width)


def _box_hits(box: Box, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, floor_z: float) -> np.ndarray:
    """Return the distance along each ray to a box (slab method; inf on a miss)."""
    lo = np.full(dx.size, -np.inf)
    hi = np.full(dx.size, np.inf)
    for d, a, b in ((dx, box.x0, box.x1), (dy, box.y0, box.y1), (dz, floor_z, floor_z + box.height)):
        t1, t2 = a / d, b / d
        lo = np.maximum(lo, np.minimum(t1, t2))
        hi = np.minimum(hi, np.maximum(t1, t2))
    return np.where((hi >= lo) & (lo > 0), lo, np.inf)


def _cylinder_hits(person: Person, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, floor_z: float) -> np.ndarray:
    """Return the distance along each ray to a person's cylinder side (inf on a miss)."""
    a = dx * dx + dy * dy
    b = -2.0 * (dx * person.x + dy * person.y)
    c = person.x**2 + person.y**2 - person.radius**2
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    z = t * dz
    ok = (disc >= 0) & (t > 0) & (z >= floor_z) & (z <= floor_z + person.height)
    return np.where(ok, t, np.inf)
