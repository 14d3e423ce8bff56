"""Nearest-hit ray casting against a compiled scene, accelerated by a uniform 2-D grid.

Scenes are 2.5-D (objects spread over the ground, not stacked), so a grid over the
ground plane lists, per cell, the primitives whose bounds overlap it, plus the cell's
height range. A ray first meets the terrain quadric analytically; that distance bounds a
2-D DDA walk (Amanatides & Woo) through the cells, which stops as soon as the best hit
lies before the current cell's exit. Cells the ray passes above or below are skipped.

The per-ray loops are numba ``prange`` kernels (see :mod:`.kernels` for why they are
hand-written); each ray is independent, so the result does not depend on thread count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from semantic3d.datasets.simulator.kernels import (
    HIT_GROUND,
    INF,
    NO_HIT,
    intersect_primitive,
    intersect_terrain,
)

MAX_GRID_CELLS = 1 << 22


@dataclass(frozen=True, slots=True)
class Grid:
    """Boxes (primitive or zone bounds) binned over the ground plane: per cell, the
    indices of the boxes overlapping it, in ascending order (compressed sparse rows)."""

    origin: NDArray[np.float64]  # (2,) lower corner
    cell_size_m: float
    shape: tuple[int, int]  # (nx, ny)
    cell_start: NDArray[np.int64]  # (nx * ny + 1,)
    cell_items: NDArray[np.int32]
    cell_zmin: NDArray[np.float64]
    cell_zmax: NDArray[np.float64]
    zmax: float


def build_grid(
    lower: NDArray[np.float64], upper: NDArray[np.float64], *, cell_size_m: float = 2.0
) -> Grid:
    """Bin boxes ``lower``–``upper`` (``(n, 3)`` each) into square ground cells."""
    if lower.shape[0] == 0:
        return Grid(
            np.zeros(2),
            1.0,
            (1, 1),
            np.zeros(2, np.int64),
            np.zeros(0, np.int32),
            np.full(1, INF),
            np.full(1, -INF),
            -INF,
        )
    lo = lower[:, :2].min(axis=0) - 1e-6
    hi = upper[:, :2].max(axis=0) + 1e-6
    cell = float(cell_size_m)
    while math.ceil((hi[0] - lo[0]) / cell) * math.ceil((hi[1] - lo[1]) / cell) > MAX_GRID_CELLS:
        cell *= 2.0
    nx = max(1, math.ceil((hi[0] - lo[0]) / cell))
    ny = max(1, math.ceil((hi[1] - lo[1]) / cell))
    start, items, zmin, zmax = _bin_boxes(lower, upper, lo, cell, nx, ny)
    return Grid(lo, cell, (nx, ny), start, items, zmin, zmax, float(upper[:, 2].max()))


@njit(cache=True)
def _bin_boxes(
    lower: np.ndarray, upper: np.ndarray, origin: np.ndarray, cell: float, nx: int, ny: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n = lower.shape[0]
    counts = np.zeros(nx * ny + 1, np.int64)
    ranges = np.empty((n, 4), np.int64)
    for p in range(n):
        ix0 = min(nx - 1, max(0, int((lower[p, 0] - origin[0]) / cell)))
        ix1 = min(nx - 1, max(0, int((upper[p, 0] - origin[0]) / cell)))
        iy0 = min(ny - 1, max(0, int((lower[p, 1] - origin[1]) / cell)))
        iy1 = min(ny - 1, max(0, int((upper[p, 1] - origin[1]) / cell)))
        ranges[p, 0] = ix0
        ranges[p, 1] = ix1
        ranges[p, 2] = iy0
        ranges[p, 3] = iy1
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                counts[iy * nx + ix + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], np.int32)
    zmin = np.full(nx * ny, np.inf)
    zmax = np.full(nx * ny, -np.inf)
    for p in range(n):
        for iy in range(ranges[p, 2], ranges[p, 3] + 1):
            for ix in range(ranges[p, 0], ranges[p, 1] + 1):
                c = iy * nx + ix
                items[fill[c]] = p
                fill[c] += 1
                zmin[c] = min(zmin[c], lower[p, 2])
                zmax[c] = max(zmax[c], upper[p, 2])
    return start, items, zmin, zmax


@njit(cache=True, inline="always")
def _hits_bounds(
    bounds: np.ndarray,
    p: int,
    ox: float,
    oy: float,
    oz: float,
    inv_x: float,
    inv_y: float,
    inv_z: float,
    t_best: float,
) -> bool:
    """Whether the ray meets the world bounds of ``p`` before ``t_best`` (a cheap pre-test:
    no rotation, no division; exact for axis-aligned boxes)."""
    a = (bounds[p, 0] - ox) * inv_x
    b = (bounds[p, 3] - ox) * inv_x
    t0 = min(a, b)
    t1 = max(a, b)
    a = (bounds[p, 1] - oy) * inv_y
    b = (bounds[p, 4] - oy) * inv_y
    t0 = max(t0, min(a, b))
    t1 = min(t1, max(a, b))
    a = (bounds[p, 2] - oz) * inv_z
    b = (bounds[p, 5] - oz) * inv_z
    t0 = max(t0, min(a, b))
    t1 = min(t1, max(a, b))
    return t0 <= t1 and t1 > 0.0 and t0 < t_best


@njit(cache=True)
def trace_ray(
    ox: float,
    oy: float,
    oz: float,
    dx: float,
    dy: float,
    dz: float,
    time_s: float,
    key: np.uint64,
    ray_id: np.uint64,
    max_range: float,
    terrain: np.ndarray,
    params: np.ndarray,
    shapes: np.ndarray,
    bounds: np.ndarray,
    grid_origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_items: np.ndarray,
    cell_zmin: np.ndarray,
    cell_zmax: np.ndarray,
    grid_zmax: float,
) -> tuple[float, int]:
    """Nearest return of one unit ray within ``max_range``: ``(distance, hit id)``; the
    distance is meaningless when the id is ``NO_HIT``."""
    t_best = intersect_terrain(terrain, ox, oy, oz, dx, dy, dz)
    best = HIT_GROUND
    if t_best > max_range:
        t_best = max_range
        best = NO_HIT
    if cell_start[-1] == 0:
        return t_best, best
    # Clip the ray to the grid rectangle.
    gx0 = grid_origin[0]
    gy0 = grid_origin[1]
    gx1 = gx0 + nx * cell
    gy1 = gy0 + ny * cell
    t_in = 0.0
    t_out = t_best
    if dx != 0.0:
        a = (gx0 - ox) / dx
        b = (gx1 - ox) / dx
        t_in = max(t_in, min(a, b))
        t_out = min(t_out, max(a, b))
    elif ox < gx0 or ox > gx1:
        return t_best, best
    if dy != 0.0:
        a = (gy0 - oy) / dy
        b = (gy1 - oy) / dy
        t_in = max(t_in, min(a, b))
        t_out = min(t_out, max(a, b))
    elif oy < gy0 or oy > gy1:
        return t_best, best
    if t_in > t_out:
        return t_best, best
    px = ox + t_in * dx
    py = oy + t_in * dy
    ix = min(nx - 1, max(0, int((px - gx0) / cell)))
    iy = min(ny - 1, max(0, int((py - gy0) / cell)))
    step_x = 1 if dx > 0.0 else -1
    step_y = 1 if dy > 0.0 else -1
    if dx != 0.0:
        next_x = (gx0 + (ix + (1 if dx > 0.0 else 0)) * cell - ox) / dx
        delta_x = cell / abs(dx)
    else:
        next_x = INF
        delta_x = INF
    if dy != 0.0:
        next_y = (gy0 + (iy + (1 if dy > 0.0 else 0)) * cell - oy) / dy
        delta_y = cell / abs(dy)
    else:
        next_y = INF
        delta_y = INF
    # Inverse direction for the bounds pre-test (a zero component gives inf, as it should).
    inv_x = 1.0 / dx if dx != 0.0 else INF
    inv_y = 1.0 / dy if dy != 0.0 else INF
    inv_z = 1.0 / dz if dz != 0.0 else INF
    t_cell = t_in
    while True:
        t_exit = min(next_x, next_y)
        c = iy * nx + ix
        begin = cell_start[c]
        end = cell_start[c + 1]
        if end > begin:
            t_far = min(t_exit, t_best)
            z_a = oz + t_cell * dz
            z_b = oz + t_far * dz
            if min(z_a, z_b) <= cell_zmax[c] and max(z_a, z_b) >= cell_zmin[c]:
                for k in range(begin, end):
                    p = cell_items[k]
                    if not _hits_bounds(bounds, p, ox, oy, oz, inv_x, inv_y, inv_z, t_best):
                        continue
                    t = intersect_primitive(
                        params, shapes, p, ox, oy, oz, dx, dy, dz, time_s, key, ray_id
                    )
                    if t < t_best:
                        t_best = t
                        best = p
        if t_best <= t_exit:
            break
        if next_x < next_y:
            ix += step_x
            if ix < 0 or ix >= nx:
                break
            t_cell = next_x
            next_x += delta_x
        else:
            iy += step_y
            if iy < 0 or iy >= ny:
                break
            t_cell = next_y
            next_y += delta_y
        if t_cell > t_best:
            break
        if dz > 0.0 and oz + t_cell * dz > grid_zmax:
            break
    return t_best, best


@njit(cache=True, nogil=True, parallel=True)
def cast_kernel(
    origin: np.ndarray,
    directions: np.ndarray,
    times: np.ndarray,
    ray_ids: np.ndarray,
    key: np.uint64,
    min_range: float,
    max_range: float,
    terrain: np.ndarray,
    params: np.ndarray,
    shapes: np.ndarray,
    bounds: np.ndarray,
    grid_origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_items: np.ndarray,
    cell_zmin: np.ndarray,
    cell_zmax: np.ndarray,
    grid_zmax: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cast every ray from ``origin``; returns distances and hit ids (``NO_HIT`` if none).

    Returns nearer than ``min_range`` are dropped, as a real scanner's would be.
    """
    n = directions.shape[0]
    distance = np.empty(n, np.float64)
    hit = np.empty(n, np.int32)
    for k in prange(n):
        t, h = trace_ray(
            origin[0],
            origin[1],
            origin[2],
            directions[k, 0],
            directions[k, 1],
            directions[k, 2],
            times[k],
            key,
            ray_ids[k],
            max_range,
            terrain,
            params,
            shapes,
            bounds,
            grid_origin,
            cell,
            nx,
            ny,
            cell_start,
            cell_items,
            cell_zmin,
            cell_zmax,
            grid_zmax,
        )
        if h == NO_HIT or t < min_range:
            t = INF
            h = NO_HIT
        distance[k] = t
        hit[k] = h
    return distance, hit
