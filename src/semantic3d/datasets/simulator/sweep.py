"""The sweep's ray geometry, computed where it is used instead of stored per ray.

Ray ``(j, i)`` of a scan is column ``j`` (azimuth ``yaw + j Δa``, scene time
``start + sweep_duration · j / n_azimuth``) and row ``i`` (elevation
``elevation_min + (i + ½) Δe``); its id is ``j · n_elevation + i``. Cosines and sines are
computed once per scan for every column and row, so a ray's direction does not depend on
which block of columns it was cast in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from semantic3d.core.atomic import row_workers, take_row_block
from semantic3d.datasets.simulator.kernels import INF, NO_HIT
from semantic3d.datasets.simulator.raycast import trace_ray


@dataclass(frozen=True, slots=True)
class SweepAngles:
    """Per-column and per-row trigonometry and timing of one scan."""

    cos_azimuth: NDArray[np.float64]
    sin_azimuth: NDArray[np.float64]
    cos_elevation: NDArray[np.float64]
    sin_elevation: NDArray[np.float64]
    start_time_s: float
    sweep_duration_s: float

    @classmethod
    def build(
        cls,
        *,
        n_azimuth: int,
        n_elevation: int,
        yaw_rad: float,
        elevation_min_rad: float,
        elevation_span_rad: float,
        start_time_s: float,
        sweep_duration_s: float,
    ) -> SweepAngles:
        """The angles of an ``n_azimuth`` × ``n_elevation`` sweep."""
        azimuth = yaw_rad + np.arange(n_azimuth) * (2.0 * math.pi / n_azimuth)
        elevation = elevation_min_rad + (np.arange(n_elevation) + 0.5) * (
            elevation_span_rad / n_elevation
        )
        return cls(
            np.cos(azimuth),
            np.sin(azimuth),
            np.cos(elevation),
            np.sin(elevation),
            float(start_time_s),
            float(sweep_duration_s),
        )

    def kernel_arguments(self) -> tuple[Any, ...]:
        """The angle and time arguments shared by the sweep kernels."""
        return (
            self.cos_azimuth,
            self.sin_azimuth,
            self.cos_elevation,
            self.sin_elevation,
            self.start_time_s,
            self.sweep_duration_s,
        )


_RAY_BLOCK = 1024  # rays per piece of work handed to a thread


@njit(cache=True, nogil=True, parallel=True)
def sweep_cast_kernel(
    origin: np.ndarray,
    first: int,
    columns: int,
    cos_azimuth: np.ndarray,
    sin_azimuth: np.ndarray,
    cos_elevation: np.ndarray,
    sin_elevation: np.ndarray,
    start_time: float,
    sweep_duration: float,
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
    n_threads: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Distances and hit ids of the rays of columns ``first .. first + columns``, on
    ``n_threads`` threads."""
    n_elevation = cos_elevation.shape[0]
    n_azimuth = cos_azimuth.shape[0]
    n = columns * n_elevation
    distance = np.empty(n, np.float64)
    hit = np.empty(n, np.int32)
    taken = np.zeros(1, np.int64)
    # blocks of rays taken as threads come free: a ray into open space crosses many grid
    # cells, one into a wall few, so equal shares of the columns are not equal work
    for _ in prange(row_workers(n_threads, n, _RAY_BLOCK)):
        while True:
            start, stop = take_row_block(taken, n, _RAY_BLOCK)
            if start >= stop:
                break
            for k in range(start, stop):
                c = k // n_elevation
                i = k - c * n_elevation
                j = first + c
                time = start_time + sweep_duration * j / n_azimuth
                t, h = trace_ray(
                    origin[0],
                    origin[1],
                    origin[2],
                    cos_elevation[i] * cos_azimuth[j],
                    cos_elevation[i] * sin_azimuth[j],
                    sin_elevation[i],
                    time,
                    key,
                    np.uint64(j * n_elevation + i),
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


@njit(cache=True, nogil=True, parallel=True)
def sweep_rays_kernel(
    block_indices: np.ndarray,
    first: int,
    cos_azimuth: np.ndarray,
    sin_azimuth: np.ndarray,
    cos_elevation: np.ndarray,
    sin_elevation: np.ndarray,
    start_time: float,
    sweep_duration: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directions, times and ids of the rays at ``block_indices`` of a block from ``first``."""
    n_elevation = cos_elevation.shape[0]
    n_azimuth = cos_azimuth.shape[0]
    n = block_indices.shape[0]
    directions = np.empty((n, 3), np.float64)
    times = np.empty(n, np.float64)
    ray_ids = np.empty(n, np.uint64)
    for m in prange(n):
        k = block_indices[m]
        c = k // n_elevation
        i = k - c * n_elevation
        j = first + c
        directions[m, 0] = cos_elevation[i] * cos_azimuth[j]
        directions[m, 1] = cos_elevation[i] * sin_azimuth[j]
        directions[m, 2] = sin_elevation[i]
        times[m] = start_time + sweep_duration * j / n_azimuth
        ray_ids[m] = np.uint64(j * n_elevation + i)
    return directions, times, ray_ids
