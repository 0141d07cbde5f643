"""People Detection's algorithms: voxel-grid sampling, then floor removal and grid clustering."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Detection", "DetectorSettings", "detect_people", "voxel_sample"]


def voxel_sample(points: np.ndarray, voxel: float, max_range: float = 12.0) -> np.ndarray:
    """Keep one point per voxel of the valid points within range ((N, 3) float32 in, (M, 3) out)."""
    points = points[np.isfinite(points).all(axis=1)]
    points = points[np.einsum("ij,ij->i", points, points) <= max_range * max_range]
    if voxel <= 0 or not len(points):
        return np.ascontiguousarray(points, dtype=np.float32)
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, first = np.unique(keys, return_index=True)
    return np.ascontiguousarray(points[np.sort(first)], dtype=np.float32)


@dataclass(frozen=True)
class DetectorSettings:
    """What counts as a person: a standing cluster of the right height and footprint."""

    cell: float = 0.1  # clustering grid, metres
    min_points_per_cell: int = 2
    floor_margin: float = 0.15  # points this close to the floor are floor
    min_height: float = 1.2
    max_height: float = 2.1
    min_width: float = 0.25
    max_width: float = 1.0
    min_points: int = 20


@dataclass(frozen=True)
class Detection:
    """A detected person: where on the floor, how tall, from how many points."""

    x: float
    y: float
    height: float
    points: int


def detect_people(points: np.ndarray, settings: DetectorSettings | None = None) -> list[Detection]:
    """Find people in a sampled cloud (camera body frame: z up): cluster what stands on the floor."""
    s = settings or DetectorSettings()
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < s.min_points:
        return []
    floor = float(np.percentile(points[:, 2], 2.0))
    # Above the floor and below anyone's head: drops floor and ceiling, which would join everything.
    standing = points[(points[:, 2] > floor + s.floor_margin) & (points[:, 2] < floor + s.max_height + 0.1)]
    if not len(standing):
        return []
    ix = np.floor(standing[:, 0] / s.cell).astype(np.int64)
    iy = np.floor(standing[:, 1] / s.cell).astype(np.int64)
    ix0, iy0 = ix.min(), iy.min()
    ix -= ix0
    iy -= iy0
    width = int(iy.max()) + 1
    keys = ix * width + iy
    cell_keys, counts = np.unique(keys, return_counts=True)
    occupied = {int(k) for k, c in zip(cell_keys, counts, strict=True) if c >= s.min_points_per_cell}
    labels: dict[int, int] = {}
    clusters = 0
    for seed in occupied:
        if seed in labels:
            continue
        labels[seed] = clusters
        stack = [seed]
        while stack:
            key = stack.pop()
            kx, ky = divmod(key, width)
            for nx in (kx - 1, kx, kx + 1):
                for ny in (ky - 1, ky, ky + 1):
                    if 0 <= ny < width:
                        other = nx * width + ny
                        if other in occupied and other not in labels:
                            labels[other] = clusters
                            stack.append(other)
        clusters += 1
    if not clusters:
        return []
    lookup_keys = np.fromiter(labels.keys(), dtype=np.int64, count=len(labels))
    lookup_vals = np.fromiter(labels.values(), dtype=np.int64, count=len(labels))
    order = np.argsort(lookup_keys)
    lookup_keys, lookup_vals = lookup_keys[order], lookup_vals[order]
    pos = np.clip(np.searchsorted(lookup_keys, keys), 0, len(lookup_keys) - 1)
    label = np.where(lookup_keys[pos] == keys, lookup_vals[pos], -1)
    found = []
    for c in range(clusters):
        member = standing[label == c]
        if len(member) < s.min_points:
            continue
        height = float(member[:, 2].max() - floor)
        extent = float(max(np.ptp(member[:, 0]), np.ptp(member[:, 1])))
        if s.min_height <= height <= s.max_height and s.min_width <= extent <= s.max_width:
            found.append(Detection(float(member[:, 0].mean()), float(member[:, 1].mean()), height, len(member)))
    return sorted(found, key=lambda d: (d.x, d.y))
