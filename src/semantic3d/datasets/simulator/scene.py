"""A scene to scan: terrain, primitives and scanner stations; and its compiled form."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.primitives import PackedPrimitives, Primitive, pack_primitives
from semantic3d.datasets.simulator.raycast import Grid, build_grid
from semantic3d.datasets.simulator.terrain import Terrain, pack_zones, zone_bounds

MAX_STATIONS = 3
"""Stations a default scene offers (the CLI's ``--stations`` runs 1..MAX_STATIONS)."""


@dataclass(frozen=True, slots=True)
class Station:
    """Where a scan is taken: the scanner's optical centre and heading in scene coordinates.

    The instrument is levelled (no roll or pitch); ``yaw_rad`` is the world azimuth of the
    scanner's zero direction, counter-clockwise from +x. ``start_time_s`` is the scene time
    at which its sweep starts (moving objects are elsewhere for each station).
    """

    number: int
    position: tuple[float, float, float]
    yaw_rad: float = 0.0
    start_time_s: float = 0.0

    def __post_init__(self) -> None:
        if self.number < 1:
            raise SimulationConfigError(f"station number: expected >= 1, found {self.number}")
        if len(self.position) != 3 or not all(math.isfinite(c) for c in self.position):
            raise SimulationConfigError(
                f"station position: expected 3 finite values, found {self.position}"
            )

    @property
    def name(self) -> str:
        """``station<number>``."""
        return f"station{self.number}"

    @property
    def matrix(self) -> NDArray[np.float64]:
        """The 4×4 scanner-to-world transform: ``world = M @ [x, y, z, 1]`` of scanner coordinates."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        matrix = np.eye(4)
        matrix[:2, :2] = [[c, -s], [s, c]]
        matrix[:3, 3] = self.position
        return matrix


@dataclass(frozen=True, slots=True)
class Scene:
    """Everything a simulated scan sees.

    Attributes:
        name: scene name (used in output file names).
        terrain: the ground and its class zones.
        primitives: the solids standing on it.
        stations: scanner stations, numbered 1..n.
    """

    name: str
    terrain: Terrain
    primitives: tuple[Primitive, ...]
    stations: tuple[Station, ...]

    def __post_init__(self) -> None:
        numbers = [s.number for s in self.stations]
        if numbers != list(range(1, len(numbers) + 1)):
            raise SimulationConfigError(
                f"scene {self.name!r}: expected stations numbered 1..n in order, found {numbers}"
            )

    def station(self, number: int) -> Station:
        """Station ``number`` (1-based)."""
        if not 1 <= number <= len(self.stations):
            raise SimulationConfigError(
                f"scene {self.name!r}: expected a station number in 1..{len(self.stations)}, "
                f"found {number}"
            )
        return self.stations[number - 1]


@dataclass(frozen=True, slots=True)
class CompiledScene:
    """A scene flattened into the arrays the kernels read."""

    scene: Scene
    primitives: PackedPrimitives
    terrain: NDArray[np.float64]
    zones: NDArray[np.float64]
    zone_labels: NDArray[np.uint8]
    bounds: NDArray[np.float64]
    """``(n, 6)`` world bounds of the primitives: lower xyz, upper xyz."""
    grid: Grid
    zone_grid: Grid
    """Zones binned like the primitives; items are zone indices (table row - 1)."""

    def kernel_arguments(self) -> tuple[Any, ...]:
        """Trailing arguments of :func:`.raycast.cast_kernel`, from the terrain on."""
        g = self.grid
        return (
            self.terrain,
            self.primitives.params,
            self.primitives.shapes,
            self.bounds,
            g.origin,
            g.cell_size_m,
            g.shape[0],
            g.shape[1],
            g.cell_start,
            g.cell_items,
            g.cell_zmin,
            g.cell_zmax,
            g.zmax,
        )

    def shade_arguments(self) -> tuple[Any, ...]:
        """Trailing arguments of :func:`.shading.shade_kernel`, from the terrain on."""
        z, p = self.zone_grid, self.primitives
        return (
            self.terrain,
            self.zones,
            self.zone_labels,
            z.origin,
            z.cell_size_m,
            z.shape[0],
            z.shape[1],
            z.cell_start,
            z.cell_items,
            p.params,
            p.shapes,
            p.labels,
        )


def compile_scene(scene: Scene, *, cell_size_m: float = 2.0) -> CompiledScene:
    """Pack ``scene`` for the kernels and bin its primitives and zones into ground grids.

    ``cell_size_m`` 2 m was the fastest of 1, 2, 4 and 8 m on the default scenes.
    """
    packed = pack_primitives(scene.primitives)
    zones, zone_labels = pack_zones(scene.terrain)
    terrain = np.asarray(scene.terrain.coefficients, np.float64)
    grid = build_grid(packed.lower, packed.upper, cell_size_m=cell_size_m)
    zone_grid = build_grid(*zone_bounds(scene.terrain), cell_size_m=4.0)
    bounds = np.ascontiguousarray(np.hstack([packed.lower, packed.upper]))
    return CompiledScene(scene, packed, terrain, zones, zone_labels, bounds, grid, zone_grid)
