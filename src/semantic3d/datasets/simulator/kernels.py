"""Numba device functions: counter-based random numbers and exact ray/solid intersections.

Hand-written because they run once per ray and per candidate primitive (hundreds of
millions of times for a full-size scan): numpy would need one temporary array per
operation, and no ray-tracing library offers porous volumes, quadric terrain or solids
that move while the scanner sweeps.

Random numbers are a pure function of ``(key, ray id, stream)`` (splitmix64 finaliser),
so a ray's noise does not depend on how rays are split into chunks or threads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from semantic3d.datasets.simulator.primitives import (
    P_CENTER,
    P_DENSITY,
    P_HALF,
    P_MOTION_DIR,
    P_PATH,
    P_PHASE,
    P_SPEED,
    P_WORLD_TO_LOCAL,
    Shape,
)

BOX = int(Shape.BOX)
CYLINDER = int(Shape.CYLINDER)
ELLIPSOID = int(Shape.ELLIPSOID)
GABLE = int(Shape.GABLE)

HIT_GROUND = -1
"""Hit id of a ray that hit the terrain."""
NO_HIT = -2
"""Hit id of a ray without a return (sky, out of range)."""

EPS = 1e-9
INF = np.inf

# Random streams (the stream of a porous primitive is STREAM_FOLIAGE + its index).
STREAM_RANGE = np.uint64(1)
STREAM_INTENSITY = np.uint64(2)
STREAM_COLOUR = np.uint64(3)
STREAM_NORMAL = np.uint64(4)
STREAM_FOLIAGE = np.uint64(1 << 20)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_P2 = np.uint64(0xC2B2AE3D27D4EB4F)
_P3 = np.uint64(0x165667B19E3779F9)
_LATTICE_OFFSET = 1 << 40


@njit(cache=True, inline="always")
def mix64(z: np.uint64) -> np.uint64:
    """splitmix64 finaliser: a bijective avalanche of 64 bits."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def uniform(key: np.uint64, ray_id: np.uint64, stream: np.uint64) -> float:
    """A uniform number in (0, 1) determined by ``(key, ray_id, stream)``."""
    h = mix64(key ^ mix64(ray_id * _GOLDEN + stream * _P2))
    return (float(h >> _S11) + 0.5) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always")
def normal_deviate(key: np.uint64, ray_id: np.uint64, stream: np.uint64) -> float:
    """A standard normal number determined by ``(key, ray_id, stream)`` (Box-Muller)."""
    u1 = uniform(key, ray_id, stream)
    u2 = uniform(key, ray_id, stream + _GOLDEN)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


@njit(cache=True, inline="always")
def lattice_noise(key: np.uint64, x: float, y: float, z: float, inv_scale: float) -> float:
    """Cell noise in [0, 1): one value per cube of side ``1 / inv_scale`` (blocky texture)."""
    ix = np.uint64(np.int64(math.floor(x * inv_scale)) + _LATTICE_OFFSET)
    iy = np.uint64(np.int64(math.floor(y * inv_scale)) + _LATTICE_OFFSET)
    iz = np.uint64(np.int64(math.floor(z * inv_scale)) + _LATTICE_OFFSET)
    h = mix64(key ^ mix64(ix * _GOLDEN ^ iy * _P2 ^ iz * _P3))
    return float(h >> _S11) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always")
def motion_offset(speed: float, length: float, phase: float, time_s: float) -> float:
    """Distance along a back-and-forth segment of ``length`` at ``time_s``."""
    period = 2.0 * length
    u = (speed * time_s + phase) % period
    return u if u <= length else period - u


@njit(cache=True, inline="always")
def _slab(o: float, d: float, h: float, t0: float, t1: float) -> tuple[float, float]:
    if d == 0.0:
        if o < -h or o > h:
            return INF, -INF
        return t0, t1
    inv = 1.0 / d
    a = (-h - o) * inv
    b = (h - o) * inv
    if a > b:
        a, b = b, a
    return max(t0, a), min(t1, b)


@njit(cache=True, inline="always")
def _half_space(
    ny: float, nz: float, c: float, oy: float, oz: float, dy: float, dz: float, t0: float, t1: float
) -> tuple[float, float]:
    """Clip ``[t0, t1]`` to ``ny * y + nz * z <= c`` (the gable's roof planes have nx = 0)."""
    denom = ny * dy + nz * dz
    num = c - (ny * oy + nz * oz)
    if denom == 0.0:
        if num < 0.0:
            return INF, -INF
        return t0, t1
    t = num / denom
    if denom < 0.0:
        return max(t0, t), t1
    return t0, min(t1, t)


@njit(cache=True, inline="always")
def _quadratic_interval(a: float, b: float, c: float) -> tuple[float, float]:
    """Roots of ``a t² + 2 b t + c`` in order, computed without cancellation; empty if none."""
    disc = b * b - a * c
    if disc < 0.0:
        return INF, -INF
    sq = math.sqrt(disc)
    q = -(b + sq) if b >= 0.0 else -(b - sq)
    if q == 0.0:
        return 0.0, 0.0
    r0 = q / a
    r1 = c / q
    if r0 > r1:
        r0, r1 = r1, r0
    return r0, r1


@njit(cache=True, inline="always")
def primitive_center(params: np.ndarray, p: int, time_s: float) -> tuple[float, float, float]:
    """Centre of primitive ``p`` at ``time_s`` (moving primitives follow their segment)."""
    cx = params[p, P_CENTER]
    cy = params[p, P_CENTER + 1]
    cz = params[p, P_CENTER + 2]
    speed = params[p, P_SPEED]
    if speed > 0.0:
        a = motion_offset(speed, params[p, P_PATH], params[p, P_PHASE], time_s)
        cx += a * params[p, P_MOTION_DIR]
        cy += a * params[p, P_MOTION_DIR + 1]
        cz += a * params[p, P_MOTION_DIR + 2]
    return cx, cy, cz


@njit(cache=True, inline="always")
def to_local(
    params: np.ndarray, p: int, x: float, y: float, z: float
) -> tuple[float, float, float]:
    """Rotate the world vector ``(x, y, z)`` into the local frame of primitive ``p``."""
    r = P_WORLD_TO_LOCAL
    lx = params[p, r] * x + params[p, r + 1] * y + params[p, r + 2] * z
    ly = params[p, r + 3] * x + params[p, r + 4] * y + params[p, r + 5] * z
    lz = params[p, r + 6] * x + params[p, r + 7] * y + params[p, r + 8] * z
    return lx, ly, lz


@njit(cache=True)
def intersect_primitive(
    params: np.ndarray,
    shapes: np.ndarray,
    p: int,
    ox: float,
    oy: float,
    oz: float,
    dx: float,
    dy: float,
    dz: float,
    time_s: float,
    key: np.uint64,
    ray_id: np.uint64,
) -> float:
    """Distance along the unit ray to its return from primitive ``p``; ``inf`` if none.

    Solids return their entry point. Porous volumes return the entry point plus an
    exponential free path, or ``inf`` when the ray leaves the volume first. A ray starting
    inside a solid gets no return from it.
    """
    cx, cy, cz = primitive_center(params, p, time_s)
    ox, oy, oz = to_local(params, p, ox - cx, oy - cy, oz - cz)
    dx, dy, dz = to_local(params, p, dx, dy, dz)
    hx = params[p, P_HALF]
    hy = params[p, P_HALF + 1]
    hz = params[p, P_HALF + 2]
    shape = shapes[p]
    t0 = -INF
    t1 = INF
    if shape in (BOX, GABLE):
        t0, t1 = _slab(ox, dx, hx, t0, t1)
        t0, t1 = _slab(oy, dy, hy, t0, t1)
        t0, t1 = _slab(oz, dz, hz, t0, t1)
        if shape == GABLE:
            slope = 2.0 * hz / hy
            t0, t1 = _half_space(slope, 1.0, hz, oy, oz, dy, dz, t0, t1)
            t0, t1 = _half_space(-slope, 1.0, hz, oy, oz, dy, dz, t0, t1)
    elif shape == CYLINDER:
        sx = ox / hx
        sy = oy / hy
        sdx = dx / hx
        sdy = dy / hy
        a = sdx * sdx + sdy * sdy
        c = sx * sx + sy * sy - 1.0
        if a < 1e-18:
            if c > 0.0:
                return INF
        else:
            r0, r1 = _quadratic_interval(a, sx * sdx + sy * sdy, c)
            t0 = max(t0, r0)
            t1 = min(t1, r1)
        t0, t1 = _slab(oz, dz, hz, t0, t1)
    else:  # ELLIPSOID
        sx = ox / hx
        sy = oy / hy
        sz = oz / hz
        sdx = dx / hx
        sdy = dy / hy
        sdz = dz / hz
        a = sdx * sdx + sdy * sdy + sdz * sdz
        r0, r1 = _quadratic_interval(
            a, sx * sdx + sy * sdy + sz * sdz, sx * sx + sy * sy + sz * sz - 1.0
        )
        t0 = r0
        t1 = r1
    if t0 > t1 or t1 <= EPS:
        return INF
    density = params[p, P_DENSITY]
    if density > 0.0:
        start = max(t0, 0.0)
        u = uniform(key, ray_id, STREAM_FOLIAGE + np.uint64(p))
        t = start - math.log(u) / density
        return t if t < t1 else INF
    if t0 <= EPS:
        return INF
    return t0


@njit(cache=True)
def intersect_terrain(
    coefficients: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float
) -> float:
    """Distance to the first crossing of the height quadric; ``inf`` if none.

    ``f(t) = z(t) - h(x(t), y(t))`` is quadratic in ``t``; the first root after a start
    above the ground is the hit. A start below the ground gets no hit.
    """
    c0 = coefficients[0]
    c1 = coefficients[1]
    c2 = coefficients[2]
    c3 = coefficients[3]
    c4 = coefficients[4]
    c5 = coefficients[5]
    h0 = c0 + c1 * ox + c2 * oy + c3 * ox * ox + c4 * ox * oy + c5 * oy * oy
    c = oz - h0
    if c <= 0.0:
        return INF
    b = dz - (
        c1 * dx + c2 * dy + 2.0 * c3 * ox * dx + c4 * (ox * dy + oy * dx) + 2.0 * c5 * oy * dy
    )
    a = -(c3 * dx * dx + c4 * dx * dy + c5 * dy * dy)
    if abs(a) < 1e-15:
        if b >= 0.0:
            return INF
        return -c / b
    r0, r1 = _quadratic_interval(a, 0.5 * b, c)
    if r0 > EPS:
        return r0
    if r1 > EPS:
        return r1
    return INF


@njit(cache=True)
def terrain_normal(coefficients: np.ndarray, x: float, y: float) -> tuple[float, float, float]:
    """Unit upward normal of the height quadric at ``(x, y)``."""
    gx = coefficients[1] + 2.0 * coefficients[3] * x + coefficients[4] * y
    gy = coefficients[2] + coefficients[4] * x + 2.0 * coefficients[5] * y
    norm = math.sqrt(gx * gx + gy * gy + 1.0)
    return -gx / norm, -gy / norm, 1.0 / norm


@njit(cache=True)
def primitive_normal(
    params: np.ndarray, shapes: np.ndarray, p: int, x: float, y: float, z: float, time_s: float
) -> tuple[float, float, float]:
    """Unit outward normal of solid ``p`` at the surface point ``(x, y, z)`` (world)."""
    cx, cy, cz = primitive_center(params, p, time_s)
    lx, ly, lz = to_local(params, p, x - cx, y - cy, z - cz)
    hx = params[p, P_HALF]
    hy = params[p, P_HALF + 1]
    hz = params[p, P_HALF + 2]
    shape = shapes[p]
    nx = 0.0
    ny = 0.0
    nz = 0.0
    if shape in (BOX, GABLE):
        # The face the point lies on is the constraint with the least slack.
        best = hx - abs(lx)
        nx = math.copysign(1.0, lx)
        slack = hy - abs(ly)
        if slack < best:
            best = slack
            nx = 0.0
            ny = math.copysign(1.0, ly)
        slack = hz - abs(lz)
        if slack < best:
            best = slack
            nx = 0.0
            ny = 0.0
            nz = math.copysign(1.0, lz)
        if shape == GABLE:
            slope = 2.0 * hz / hy
            norm = math.sqrt(1.0 + slope * slope)
            slack = (hz - lz - slope * abs(ly)) / norm
            if slack < best:
                nx = 0.0
                ny = math.copysign(slope, ly) / norm
                nz = 1.0 / norm
    elif shape == CYLINDER:
        radial = math.sqrt((lx / hx) ** 2 + (ly / hy) ** 2)
        if (1.0 - radial) * min(hx, hy) < hz - abs(lz):
            nx = lx / (hx * hx)
            ny = ly / (hy * hy)
        else:
            nz = math.copysign(1.0, lz)
    else:
        nx = lx / (hx * hx)
        ny = ly / (hy * hy)
        nz = lz / (hz * hz)
    # Back to world: the transpose of the world-to-local rotation.
    r = P_WORLD_TO_LOCAL
    wx = params[p, r] * nx + params[p, r + 3] * ny + params[p, r + 6] * nz
    wy = params[p, r + 1] * nx + params[p, r + 4] * ny + params[p, r + 7] * nz
    wz = params[p, r + 2] * nx + params[p, r + 5] * ny + params[p, r + 8] * nz
    norm = math.sqrt(wx * wx + wy * wy + wz * wz)
    if norm == 0.0:
        return 0.0, 0.0, 1.0
    return wx / norm, wy / norm, wz / norm
