"""``SceneBuilder``: collects primitives, ground zones and stations while a scene is laid out."""

from __future__ import annotations

import math

import numpy as np

from semantic3d.core import class_by_name
from semantic3d.datasets.simulator.primitives import Motion, Primitive, Shape, Surface
from semantic3d.datasets.simulator.scene import Scene, Station
from semantic3d.datasets.simulator.terrain import Terrain, Zone, ZoneShape

MAN_MADE_TERRAIN = class_by_name("man-made terrain").value
NATURAL_TERRAIN = class_by_name("natural terrain").value
HIGH_VEGETATION = class_by_name("high vegetation").value
LOW_VEGETATION = class_by_name("low vegetation").value
BUILDINGS = class_by_name("buildings").value
HARD_SCAPE = class_by_name("hard scape").value
SCANNING_ARTEFACTS = class_by_name("scanning artefacts").value
CARS = class_by_name("cars").value

STATION_INTERVAL_S = 900.0
"""Scene time between the starts of two stations' sweeps."""


class SceneBuilder:
    """Mutable helper that lays out a scene; :meth:`build` freezes it into a :class:`Scene`.

    ``rng`` (seeded) drives every random choice of the layout, so a seed fixes the scene.
    """

    def __init__(self, name: str, terrain: Terrain, *, seed: int) -> None:
        self.name = name
        self.terrain = terrain
        self.rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,)))
        self.primitives: list[Primitive] = []
        self.zones: list[Zone] = list(terrain.zones)
        self.stations: list[Station] = []

    def ground(self, x: float, y: float) -> float:
        """Terrain height at ``(x, y)``."""
        return float(self.terrain.height_at(x, y))

    def add(
        self,
        shape: Shape,
        center: tuple[float, float, float],
        half_size: tuple[float, float, float],
        label: int,
        surface: Surface,
        *,
        yaw_rad: float = 0.0,
        pitch_rad: float = 0.0,
        roll_rad: float = 0.0,
        density_per_m: float = 0.0,
        motion: Motion | None = None,
    ) -> None:
        """Append one primitive."""
        self.primitives.append(
            Primitive(
                shape,
                center,
                half_size,
                label,
                surface,
                yaw_rad,
                pitch_rad,
                roll_rad,
                density_per_m,
                motion,
            )
        )

    def add_local_box(
        self,
        origin: tuple[float, float, float],
        yaw_rad: float,
        offset: tuple[float, float, float],
        half_size: tuple[float, float, float],
        label: int,
        surface: Surface,
        *,
        shape: Shape = Shape.BOX,
        motion: Motion | None = None,
    ) -> None:
        """Append a solid placed at ``offset`` in the frame of an object at ``origin``/``yaw``."""
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        x = origin[0] + c * offset[0] - s * offset[1]
        y = origin[1] + s * offset[0] + c * offset[1]
        self.add(
            shape,
            (x, y, origin[2] + offset[2]),
            half_size,
            label,
            surface,
            yaw_rad=yaw_rad,
            motion=motion,
        )

    def zone(
        self,
        center: tuple[float, float],
        half_size: tuple[float, float],
        label: int,
        surface: Surface,
        *,
        yaw_rad: float = 0.0,
        ellipse: bool = False,
    ) -> None:
        """Paint a ground zone over the previous ones."""
        shape = ZoneShape.ELLIPSE if ellipse else ZoneShape.RECTANGLE
        self.zones.append(Zone(shape, center, half_size, label, surface, yaw_rad))

    def station(
        self, x: float, y: float, *, yaw_rad: float | None = None, floor_z: float | None = None
    ) -> None:
        """Set up the next station over ``(x, y)`` on a tripod 1.5–2 m above the floor.

        ``floor_z`` is the height of what the tripod stands on (the terrain by default).
        """
        height = float(self.rng.uniform(1.55, 1.95))
        yaw = float(self.rng.uniform(-math.pi, math.pi)) if yaw_rad is None else yaw_rad
        floor = self.ground(x, y) if floor_z is None else floor_z
        number = len(self.stations) + 1
        self.stations.append(
            Station(number, (x, y, floor + height), yaw, (number - 1) * STATION_INTERVAL_S)
        )

    def build(self) -> Scene:
        """The finished scene."""
        terrain = Terrain(
            self.terrain.coefficients, self.terrain.label, self.terrain.surface, tuple(self.zones)
        )
        return Scene(self.name, terrain, tuple(self.primitives), tuple(self.stations))


def segment_distance(x0: float, y0: float, x1: float, y1: float, px: float, py: float) -> float:
    """Distance from ``(px, py)`` to the segment ``(x0, y0)-(x1, y1)``.

    >>> segment_distance(0.0, 0.0, 10.0, 0.0, 5.0, 2.0)
    2.0
    """
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    f = 0.0 if length2 == 0.0 else min(1.0, max(0.0, ((px - x0) * dx + (py - y0) * dy) / length2))
    return math.hypot(x0 + f * dx - px, y0 + f * dy - py)
