"""The ground: a gentle quadric height field split into class zones.

The height is ``z = c0 + c1 x + c2 y + c3 x² + c4 x y + c5 y²``: a ray meets it where a
quadratic in the ray parameter vanishes, so the hit is exact (no marching). The relief is
gentle by construction (scenes keep the curvature terms tiny); mounds and embankments
are added as half-buried ellipsoids labelled natural terrain.

Which class and surface a ground hit gets is decided by :class:`Zone` regions painted
over the ground (roads, pavements, squares, gardens); the last zone containing the point
wins, and points in no zone get the terrain's base class and surface.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core import N_CLASSES
from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.primitives import Surface, pack_surface


class ZoneShape(IntEnum):
    """The outline of a ground zone in its local frame."""

    RECTANGLE = 0
    """``|u| <= hu, |v| <= hv``."""
    ELLIPSE = 1
    """``(u/hu)² + (v/hv)² <= 1``."""


@dataclass(frozen=True, slots=True)
class Zone:
    """A region of the ground with its own class and surface (a road, a lawn, a square)."""

    shape: ZoneShape
    center: tuple[float, float]
    half_size: tuple[float, float]
    label: int
    surface: Surface
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        if not 1 <= self.label <= N_CLASSES:
            raise SimulationConfigError(
                f"zone label: expected a class value 1..{N_CLASSES}, found {self.label}"
            )
        if len(self.half_size) != 2 or not all(h > 0.0 for h in self.half_size):
            raise SimulationConfigError(
                f"zone half_size: expected 2 values > 0, found {self.half_size}"
            )

    def contains(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.bool_]:
        """Whether the points ``(x, y)`` lie in the zone."""
        dx = np.asarray(x, np.float64) - self.center[0]
        dy = np.asarray(y, np.float64) - self.center[1]
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        u = (c * dx + s * dy) / self.half_size[0]
        v = (-s * dx + c * dy) / self.half_size[1]
        if self.shape is ZoneShape.ELLIPSE:
            return np.asarray(u * u + v * v <= 1.0)
        return np.asarray((np.abs(u) <= 1.0) & (np.abs(v) <= 1.0))


@dataclass(frozen=True, slots=True)
class Terrain:
    """The ground surface and its zones.

    Attributes:
        coefficients: ``(c0, c1, c2, c3, c4, c5)`` of the height quadric (metres).
        label: class of ground in no zone (natural terrain by default).
        surface: surface of ground in no zone.
        zones: painted regions, later ones on top.
    """

    coefficients: tuple[float, float, float, float, float, float]
    label: int
    surface: Surface
    zones: tuple[Zone, ...] = ()

    def __post_init__(self) -> None:
        if len(self.coefficients) != 6 or not all(math.isfinite(c) for c in self.coefficients):
            raise SimulationConfigError(
                f"terrain coefficients: expected 6 finite values, found {self.coefficients}"
            )
        if not 1 <= self.label <= N_CLASSES:
            raise SimulationConfigError(
                f"terrain label: expected a class value 1..{N_CLASSES}, found {self.label}"
            )

    def height_at(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """Ground height at ``(x, y)``."""
        c0, c1, c2, c3, c4, c5 = self.coefficients
        xa = np.asarray(x, np.float64)
        ya = np.asarray(y, np.float64)
        return np.asarray(c0 + c1 * xa + c2 * ya + c3 * xa * xa + c4 * xa * ya + c5 * ya * ya)

    def label_at(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.uint8]:
        """Class label of the ground at ``(x, y)`` (zones painted in order over the base)."""
        xa = np.asarray(x, np.float64)
        labels = np.full(xa.shape, self.label, np.uint8)
        for zone in self.zones:
            labels[zone.contains(xa, y)] = zone.label
        return labels


# Column layout of the packed zone table.
Z_SHAPE = 0
Z_CENTER = 1  # 2
Z_COS = 3
Z_SIN = 4
Z_INV_HALF = 5  # 2: 1 / half sizes
Z_RGB = 7  # surface: 7 values, same order as primitives
N_ZONE_PARAMS = 14


def pack_zones(terrain: Terrain) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """The zones as a ``(n_zones + 1, N_ZONE_PARAMS)`` table and labels; row 0 is the base."""
    zones: Sequence[Zone] = terrain.zones
    params = np.zeros((len(zones) + 1, N_ZONE_PARAMS), np.float64)
    labels = np.zeros(len(zones) + 1, np.uint8)
    params[0, Z_SHAPE] = -1.0
    pack_surface(terrain.surface, params[0], Z_RGB)
    labels[0] = terrain.label
    for i, zone in enumerate(zones, start=1):
        row = params[i]
        row[Z_SHAPE] = float(zone.shape)
        row[Z_CENTER : Z_CENTER + 2] = zone.center
        row[Z_COS] = math.cos(zone.yaw_rad)
        row[Z_SIN] = math.sin(zone.yaw_rad)
        row[Z_INV_HALF] = 1.0 / zone.half_size[0]
        row[Z_INV_HALF + 1] = 1.0 / zone.half_size[1]
        pack_surface(zone.surface, row, Z_RGB)
        labels[i] = zone.label
    return params, labels


def zone_bounds(terrain: Terrain) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Axis-aligned ``(lower, upper)`` ``(n_zones, 3)`` bounds of the zones (z is 0)."""
    n = len(terrain.zones)
    lower = np.zeros((n, 3), np.float64)
    upper = np.zeros((n, 3), np.float64)
    for i, zone in enumerate(terrain.zones):
        c, s = abs(math.cos(zone.yaw_rad)), abs(math.sin(zone.yaw_rad))
        hu, hv = zone.half_size
        extent = np.array([c * hu + s * hv, s * hu + c * hv])
        lower[i, :2] = np.asarray(zone.center) - extent
        upper[i, :2] = np.asarray(zone.center) + extent
    return lower, upper
