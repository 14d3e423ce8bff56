"""What the scanner records at each hit: noisy position, intensity, colour and label.

- position: the true hit moved along the ray by Gaussian range noise;
- intensity: surface reflectance times ``0.2 + 0.8 cos(incidence)``, attenuated with range,
  plus a little noise, mapped to the signed integer range of Semantic3D scans
  (``INTENSITY_MIN..INTENSITY_MAX``);
- colour: the surface's base colour with blocky two-octave texture (patches, tiles) lit
  by a fixed sun, plus per-point noise;
- label: the class of the primitive hit, or of the ground zone under a terrain hit.

Porous volumes (foliage) have no surface normal: each return gets a random leaf normal.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from semantic3d.core.atomic import row_workers, take_row_block
from semantic3d.datasets.simulator.kernels import (
    HIT_GROUND,
    STREAM_COLOUR,
    STREAM_INTENSITY,
    STREAM_NORMAL,
    STREAM_RANGE,
    lattice_noise,
    mix64,
    normal_deviate,
    primitive_normal,
    terrain_normal,
    uniform,
)
from semantic3d.datasets.simulator.primitives import P_DENSITY, P_RGB
from semantic3d.datasets.simulator.terrain import (
    Z_CENTER,
    Z_COS,
    Z_INV_HALF,
    Z_RGB,
    Z_SHAPE,
    Z_SIN,
)

INTENSITY_MIN = -2048
INTENSITY_MAX = 2047
INTENSITY_NOISE = 0.01
INTENSITY_HALF_RANGE_M = 150.0
"""Range at which the recorded intensity of a surface has dropped by half."""

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_P2 = np.uint64(0xC2B2AE3D27D4EB4F)
_MASK16 = np.uint64(0xFFFF)
_S16 = np.uint64(16)
_S32 = np.uint64(32)
_S48 = np.uint64(48)
_SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
_TEXTURE_KEY = np.uint64(0x5851F42D4C957F2D)
_DETAIL_KEY = np.uint64(0x14057B7EF767814F)


@njit(cache=True)
def zone_at(
    zones: np.ndarray,
    x: float,
    y: float,
    grid_origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_items: np.ndarray,
) -> int:
    """Row of the zone table painting ``(x, y)``: the last containing zone, else 0 (base)."""
    ix = math.floor((x - grid_origin[0]) / cell)
    iy = math.floor((y - grid_origin[1]) / cell)
    if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
        return 0
    c = iy * nx + ix
    for k in range(cell_start[c + 1] - 1, cell_start[c] - 1, -1):
        z = cell_items[k] + 1
        dx = x - zones[z, Z_CENTER]
        dy = y - zones[z, Z_CENTER + 1]
        u = (zones[z, Z_COS] * dx + zones[z, Z_SIN] * dy) * zones[z, Z_INV_HALF]
        v = (-zones[z, Z_SIN] * dx + zones[z, Z_COS] * dy) * zones[z, Z_INV_HALF + 1]
        if zones[z, Z_SHAPE] == 1.0:
            if u * u + v * v <= 1.0:
                return z
        elif abs(u) <= 1.0 and abs(v) <= 1.0:
            return z
    return 0


@njit(cache=True, inline="always")
def approximate_normal(key: np.uint64, ray_id: np.uint64, stream: np.uint64) -> float:
    """A cheap near-normal deviate (Irwin-Hall: four 16-bit uniforms from one hash).

    Used for intensity and colour noise, where the exact tail shape does not matter and a
    Box-Muller pair per channel would dominate the shading time.
    """
    h = mix64(key ^ mix64(ray_id * _GOLDEN + stream * _P2))
    total = float(h & _MASK16) + float((h >> _S16) & _MASK16)
    total += float((h >> _S32) & _MASK16) + float(h >> _S48)
    return (total - 131070.0) * (1.0 / 37837.23)


_POINT_BLOCK = 1024  # points per piece of work handed to a thread


@njit(cache=True, nogil=True, parallel=True)
def shade_kernel(
    origin: np.ndarray,
    directions: np.ndarray,
    distance: np.ndarray,
    hit: np.ndarray,
    returned: np.ndarray,
    times: np.ndarray,
    ray_ids: np.ndarray,
    key: np.uint64,
    range_noise_m: float,
    terrain: np.ndarray,
    zones: np.ndarray,
    zone_labels: np.ndarray,
    zone_origin: np.ndarray,
    zone_cell: float,
    zone_nx: int,
    zone_ny: int,
    zone_start: np.ndarray,
    zone_items: np.ndarray,
    params: np.ndarray,
    shapes: np.ndarray,
    labels: np.ndarray,
    n_threads: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points, intensities, colours and labels of the hits of rays ``returned`` (indices
    into ``distance`` and ``hit``; ``directions``, ``times`` and ``ray_ids`` are theirs, in
    that order), on ``n_threads`` threads."""
    n = directions.shape[0]
    xyz = np.empty((n, 3), np.float64)
    intensity = np.empty(n, np.int32)
    rgb = np.empty((n, 3), np.uint8)
    out_labels = np.empty(n, np.uint8)
    sun_x, sun_y, sun_z = _SUN[0], _SUN[1], _SUN[2]
    taken = np.zeros(1, np.int64)
    # blocks of points taken as threads come free: ground and each kind of primitive
    # cost their own time, so equal shares of the points are not equal work
    for _ in prange(row_workers(n_threads, n, _POINT_BLOCK)):
        while True:
            start, stop = take_row_block(taken, n, _POINT_BLOCK)
            if start >= stop:
                break
            for k in range(start, stop):
                dx = directions[k, 0]
                dy = directions[k, 1]
                dz = directions[k, 2]
                t = distance[returned[k]]
                ray = ray_ids[k]
                x = origin[0] + t * dx
                y = origin[1] + t * dy
                z = origin[2] + t * dz
                h = hit[returned[k]]
                if h == HIT_GROUND:
                    nx, ny, nz = terrain_normal(terrain, x, y)
                    table = zones
                    row = zone_at(
                        zones,
                        x,
                        y,
                        zone_origin,
                        zone_cell,
                        zone_nx,
                        zone_ny,
                        zone_start,
                        zone_items,
                    )
                    start = Z_RGB
                    label = zone_labels[row]
                else:
                    table = params
                    row = h
                    start = P_RGB
                    label = labels[h]
                    if params[h, P_DENSITY] > 0.0:
                        # A leaf: random orientation, facing the scanner.
                        cz = 2.0 * uniform(key, ray, STREAM_NORMAL) - 1.0
                        phi = 2.0 * math.pi * uniform(key, ray, STREAM_NORMAL + np.uint64(1))
                        sz = math.sqrt(max(0.0, 1.0 - cz * cz))
                        nx, ny, nz = sz * math.cos(phi), sz * math.sin(phi), cz
                    else:
                        nx, ny, nz = primitive_normal(params, shapes, h, x, y, z, times[k])
                cos_incidence = -(nx * dx + ny * dy + nz * dz)
                if cos_incidence < 0.0:
                    nx, ny, nz = -nx, -ny, -nz
                    cos_incidence = -cos_incidence
                # Range noise along the ray.
                t_noisy = t + range_noise_m * normal_deviate(key, ray, STREAM_RANGE)
                xyz[k, 0] = origin[0] + t_noisy * dx
                xyz[k, 1] = origin[1] + t_noisy * dy
                xyz[k, 2] = origin[2] + t_noisy * dz
                # Intensity from reflectance, incidence and range.
                r_rel = t / INTENSITY_HALF_RANGE_M
                value = table[row, start + 3] * (0.2 + 0.8 * cos_incidence) / (1.0 + r_rel * r_rel)
                value += INTENSITY_NOISE * approximate_normal(key, ray, STREAM_INTENSITY)
                value = min(1.0, max(0.0, value))
                intensity[k] = INTENSITY_MIN + round(value * (INTENSITY_MAX - INTENSITY_MIN))
                # Colour: base x texture x sun + noise.
                inv_scale = 1.0 / table[row, start + 5]
                coarse = lattice_noise(_TEXTURE_KEY, x, y, z, inv_scale) - 0.5
                fine = lattice_noise(_DETAIL_KEY, x, y, z, 4.0 * inv_scale) - 0.5
                texture = 1.0 + table[row, start + 4] * (1.4 * coarse + 0.6 * fine)
                sun = 0.7 + 0.3 * max(0.0, nx * sun_x + ny * sun_y + nz * sun_z)
                for channel in range(3):
                    noise = table[row, start + 6] * normal_deviate(
                        key, ray, STREAM_COLOUR + np.uint64(channel)
                    )
                    value = table[row, start + channel] * texture * sun + noise
                    rgb[k, channel] = np.uint8(min(255.0, max(0.0, round(value))))
                out_labels[k] = label
    return xyz, intensity, rgb, out_labels


@njit(cache=True, nogil=True, parallel=True)
def zone_labels_kernel(
    xy: np.ndarray,
    zones: np.ndarray,
    zone_labels: np.ndarray,
    zone_origin: np.ndarray,
    zone_cell: float,
    zone_nx: int,
    zone_ny: int,
    zone_start: np.ndarray,
    zone_items: np.ndarray,
) -> np.ndarray:
    """Label values of the ground zones under the points ``xy`` (``(n, 2)``)."""
    n = xy.shape[0]
    out = np.empty(n, np.uint8)
    for k in prange(n):
        row = zone_at(
            zones,
            xy[k, 0],
            xy[k, 1],
            zone_origin,
            zone_cell,
            zone_nx,
            zone_ny,
            zone_start,
            zone_items,
        )
        out[k] = zone_labels[row]
    return out
