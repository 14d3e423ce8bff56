"""The static terrestrial laser scanner: configuration, resolution planning and the sweep.

The instrument is panoramic: its head turns slowly through 360° of azimuth while a mirror
sweeps each column of elevations quickly, so every column has one time stamp. Angular
steps are equal in azimuth and elevation and chosen so a scan has about ``n_points``
returns: a coarse pilot sweep measures the fraction of rays that come back (the rest go
to the sky or beyond range) and the step follows from it. Point density therefore falls
with range² (and further with grazing incidence), and whatever stands in front of a
surface leaves a shadow on it.

Randomness (range noise, foliage free paths, colour noise) is a pure function of the seed,
the station and each ray's index, so results do not depend on ``chunk_size`` or threads.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core import PointCloud
from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.kernels import HIT_GROUND, NO_HIT
from semantic3d.datasets.simulator.raycast import cast_kernel
from semantic3d.datasets.simulator.scene import CompiledScene, Scene, Station, compile_scene
from semantic3d.datasets.simulator.shading import shade_kernel, zone_labels_kernel
from semantic3d.datasets.simulator.sweep import SweepAngles, sweep_cast_kernel, sweep_rays_kernel
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, rechunk, validate_chunk_size

PILOT_STEP_DEG = 0.75
"""Angular step of the pilot sweep that measures a station's return ratio."""
MAX_POINTS = 2_000_000_000


@dataclass(frozen=True, slots=True)
class Scanner:
    """The instrument (defaults resemble a phase-based panoramic scanner).

    Attributes:
        min_range_m: returns nearer than this are not recorded.
        max_range_m: returns farther than this are not recorded.
        range_noise_m: standard deviation of the range noise.
        elevation_min_deg, elevation_max_deg: vertical field of view (the tripod hides
            the cone below ``elevation_min_deg``).
        sweep_duration_s: time for the head to turn through 360°; moving objects move
            this long while the scan is taken.
    """

    min_range_m: float = 0.6
    max_range_m: float = 250.0
    range_noise_m: float = 0.002
    elevation_min_deg: float = -60.0
    elevation_max_deg: float = 90.0
    sweep_duration_s: float = 180.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise SimulationConfigError(
                "scanner ranges: expected 0 <= min_range_m < max_range_m, found "
                f"{self.min_range_m}, {self.max_range_m}"
            )
        if not -90.0 <= self.elevation_min_deg < self.elevation_max_deg <= 90.0:
            raise SimulationConfigError(
                "scanner elevations: expected -90 <= elevation_min_deg < elevation_max_deg <= 90,"
                f" found {self.elevation_min_deg}, {self.elevation_max_deg}"
            )
        if self.range_noise_m < 0.0 or self.sweep_duration_s < 0.0:
            raise SimulationConfigError(
                "scanner: expected range_noise_m >= 0 and sweep_duration_s >= 0, found "
                f"{self.range_noise_m}, {self.sweep_duration_s}"
            )

    @property
    def elevation_span_rad(self) -> float:
        """Vertical field of view in radians."""
        return math.radians(self.elevation_max_deg - self.elevation_min_deg)


@dataclass(frozen=True, slots=True)
class ScanPlan:
    """The angular sampling of one scan."""

    n_azimuth: int
    n_elevation: int
    azimuth_step_rad: float
    elevation_step_rad: float
    return_ratio: float
    """Fraction of the pilot sweep's rays that returned."""

    @property
    def n_rays(self) -> int:
        """Rays the sweep casts."""
        return self.n_azimuth * self.n_elevation

    @property
    def expected_points(self) -> int:
        """Returns expected from the pilot's return ratio."""
        return round(self.return_ratio * self.n_rays)


@dataclass(frozen=True, slots=True)
class RayHits:
    """What rays hit: distance (``inf`` without return), primitive index, label value.

    ``primitive`` is an index into ``scene.primitives``, ``HIT_GROUND`` (-1) for the
    terrain or ``NO_HIT`` (-2); ``labels`` is 0 where there is no return.
    """

    distance_m: NDArray[np.float64]
    primitive: NDArray[np.int32]
    labels: NDArray[np.uint8]


def validate_n_points(n_points: int) -> int:
    """``n_points`` as an int, or :class:`SimulationConfigError` unless 1..MAX_POINTS."""
    if isinstance(n_points, bool) or int(n_points) != n_points or not 1 <= n_points <= MAX_POINTS:
        raise SimulationConfigError(
            f"n_points: expected an integer in 1..{MAX_POINTS:_}, found {n_points!r}"
        )
    return int(n_points)


def station_key(seed: int, station: Station, stream: int = 0) -> np.uint64:
    """The 64-bit random key of ``station``'s scan (``stream`` 1 for its pilot sweep)."""
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise SimulationConfigError(f"seed: expected a non-negative integer, found {seed!r}")
    sequence = np.random.SeedSequence(int(seed), spawn_key=(station.number, stream))
    return np.uint64(sequence.generate_state(1, np.uint64)[0])


def plan_scan(
    scene: Scene | CompiledScene,
    station: Station,
    *,
    n_points: int,
    scanner: Scanner = Scanner(),
    seed: int = 0,
) -> ScanPlan:
    """Choose the angular step giving about ``n_points`` returns from ``station``."""
    n_points = validate_n_points(n_points)
    compiled = scene if isinstance(scene, CompiledScene) else compile_scene(scene)
    pilot_step = math.radians(PILOT_STEP_DEG)
    pilot = _uniform_plan(scanner, pilot_step, 1.0)
    key = station_key(seed, station, 1)
    angles = _angles(station, scanner, pilot)
    hits = 0
    for first in range(0, pilot.n_azimuth, 64):
        columns = min(64, pilot.n_azimuth - first)
        _, hit = _cast_columns(compiled, station, scanner, angles, first, columns, key)
        hits += int(np.count_nonzero(hit != NO_HIT))
    ratio = hits / pilot.n_rays
    if hits == 0:
        raise SimulationConfigError(
            f"scene {compiled.scene.name!r}, {station.name}: the pilot sweep got no returns; "
            "expected something within range of the scanner"
        )
    step = math.sqrt(2.0 * math.pi * scanner.elevation_span_rad * ratio / n_points)
    return _uniform_plan(scanner, step, ratio)


def simulate_scan(
    scene: Scene | CompiledScene,
    station: Station,
    *,
    n_points: int,
    seed: int = 0,
    scanner: Scanner = Scanner(),
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    plan: ScanPlan | None = None,
) -> Iterator[PointCloud]:
    """Scan ``scene`` from ``station``: labelled chunks of exactly ``chunk_size`` points.

    Points are in scene (world) coordinates, in sweep order (column by column). ``plan``
    skips the pilot sweep when the caller already ran :func:`plan_scan` with the same
    arguments. Arguments are checked before the first chunk is asked for.
    """
    n_points = validate_n_points(n_points)
    try:
        chunk_size = validate_chunk_size(chunk_size)
    except ValueError as exc:
        raise SimulationConfigError(str(exc)) from None
    compiled = scene if isinstance(scene, CompiledScene) else compile_scene(scene)
    if plan is None:
        plan = plan_scan(compiled, station, n_points=n_points, scanner=scanner, seed=seed)
    pieces = iter_sweep_blocks(
        compiled, station, plan=plan, seed=seed, scanner=scanner, chunk_size=chunk_size
    )
    return rechunk(pieces, chunk_size, PointCloud.concatenate)


def iter_sweep_blocks(
    compiled: CompiledScene,
    station: Station,
    *,
    plan: ScanPlan,
    seed: int,
    scanner: Scanner,
    chunk_size: int,
) -> Iterator[PointCloud]:
    """The returns of blocks of whole columns of about ``chunk_size`` rays (sizes vary).

    :func:`simulate_scan` regroups them into exact chunks; writers that do not need exact
    chunks take them as they come and skip the copy.
    """
    key = station_key(seed, station)
    angles = _angles(station, scanner, plan)
    columns_per_block = max(1, chunk_size // plan.n_elevation)
    for first in range(0, plan.n_azimuth, columns_per_block):
        columns = min(columns_per_block, plan.n_azimuth - first)
        distance, hit = _cast_columns(compiled, station, scanner, angles, first, columns, key)
        returned = np.flatnonzero(hit != NO_HIT)
        if returned.size:
            yield _shade(compiled, station, scanner, key, angles, first, distance, hit, returned)


def cast_rays(
    scene: Scene | CompiledScene,
    origin: ArrayLike,
    directions: ArrayLike,
    *,
    times_s: ArrayLike = 0.0,
    seed: int = 0,
    scanner: Scanner = Scanner(),
) -> RayHits:
    """Cast rays from ``origin`` along ``directions`` (normalised here) and report hits.

    ``times_s`` (scalar or one per ray) places moving objects; ``seed`` drives the free
    paths through porous volumes. Ranges outside the scanner's are no return.
    """
    compiled = scene if isinstance(scene, CompiledScene) else compile_scene(scene)
    origin_arr = np.ascontiguousarray(np.asarray(origin, np.float64).reshape(3))
    dirs = np.asarray(directions, np.float64).reshape(-1, 3)
    norms = np.linalg.norm(dirs, axis=1, keepdims=True)
    if not np.all(norms > 0.0):
        raise SimulationConfigError("cast_rays: expected non-zero direction vectors, found zeros")
    dirs = np.ascontiguousarray(dirs / norms)
    # A writable copy: a read-only view would be another compilation of the kernel.
    times = np.array(np.broadcast_to(np.asarray(times_s, np.float64), len(dirs)))
    ray_ids = np.arange(len(dirs), dtype=np.uint64)
    key = station_key(seed, Station(1, (0.0, 0.0, 0.0)))
    distance, hit = cast_kernel(
        origin_arr,
        dirs,
        times,
        ray_ids,
        key,
        scanner.min_range_m,
        scanner.max_range_m,
        *compiled.kernel_arguments(),
    )
    labels = np.zeros(len(dirs), np.uint8)
    solid = hit >= 0
    labels[solid] = compiled.primitives.labels[hit[solid]]
    ground = hit == HIT_GROUND
    xy = np.ascontiguousarray(origin_arr[:2] + distance[ground, None] * dirs[ground, :2])
    labels[ground] = zone_labels_kernel(xy, *compiled.shade_arguments()[1:9])
    return RayHits(distance, hit, labels)


def _uniform_plan(scanner: Scanner, step: float, ratio: float) -> ScanPlan:
    n_azimuth = max(1, round(2.0 * math.pi / step))
    n_elevation = max(1, round(scanner.elevation_span_rad / step))
    return ScanPlan(
        n_azimuth,
        n_elevation,
        2.0 * math.pi / n_azimuth,
        scanner.elevation_span_rad / n_elevation,
        ratio,
    )


def _angles(station: Station, scanner: Scanner, plan: ScanPlan) -> SweepAngles:
    return SweepAngles.build(
        n_azimuth=plan.n_azimuth,
        n_elevation=plan.n_elevation,
        yaw_rad=station.yaw_rad,
        elevation_min_rad=math.radians(scanner.elevation_min_deg),
        elevation_span_rad=scanner.elevation_span_rad,
        start_time_s=station.start_time_s,
        sweep_duration_s=scanner.sweep_duration_s,
    )


def _cast_columns(
    compiled: CompiledScene,
    station: Station,
    scanner: Scanner,
    angles: SweepAngles,
    first: int,
    columns: int,
    key: np.uint64,
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    origin = np.asarray(station.position, np.float64)
    arguments = (
        origin,
        first,
        columns,
        *angles.kernel_arguments(),
        key,
        scanner.min_range_m,
        scanner.max_range_m,
        *compiled.kernel_arguments(),
        numba.get_num_threads(),
    )
    return sweep_cast_kernel(*arguments)


def _shade(
    compiled: CompiledScene,
    station: Station,
    scanner: Scanner,
    key: np.uint64,
    angles: SweepAngles,
    first: int,
    distance: NDArray[np.float64],
    hit: NDArray[np.int32],
    returned: NDArray[np.intp],
) -> PointCloud:
    directions, times, ray_ids = sweep_rays_kernel(returned, first, *angles.kernel_arguments())
    arguments = (
        np.asarray(station.position, np.float64),
        directions,
        distance,
        hit,
        returned,
        times,
        ray_ids,
        key,
        scanner.range_noise_m,
        *compiled.shade_arguments(),
        numba.get_num_threads(),
    )
    xyz, intensity, rgb, labels = shade_kernel(*arguments)
    return PointCloud(xyz, intensity, rgb, labels)
