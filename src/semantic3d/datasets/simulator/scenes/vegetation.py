"""Trees (trunk + porous crown lobes), bushes, hedges and flower beds."""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.primitives import Shape
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import (
    HIGH_VEGETATION,
    LOW_VEGETATION,
    NATURAL_TERRAIN,
    SceneBuilder,
)


def tree(
    b: SceneBuilder,
    x: float,
    y: float,
    *,
    height_m: float | None = None,
    conifer: bool = False,
    pit_radius_m: float = 0.0,
) -> None:
    """A tree; ``pit_radius_m > 0`` paints a disc of bare earth around the trunk."""
    rng = b.rng
    height = float(rng.uniform(7.0, 16.0)) if height_m is None else height_m
    z = b.ground(x, y)
    if pit_radius_m > 0.0:
        b.zone((x, y), (pit_radius_m, pit_radius_m), NATURAL_TERRAIN, palette.EARTH, ellipse=True)
    trunk_radius = 0.1 + 0.018 * height
    if conifer:
        crown_base = z + height * float(rng.uniform(0.15, 0.3))
        half_height = (z + height - crown_base) / 2
        radius = half_height * float(rng.uniform(0.35, 0.5))
        b.add(
            Shape.CYLINDER,
            (x, y, (z - 0.3 + crown_base + half_height) / 2),
            (trunk_radius, trunk_radius, (crown_base + half_height - z + 0.3) / 2),
            HIGH_VEGETATION,
            palette.BARK,
        )
        b.add(
            Shape.ELLIPSOID,
            (x, y, crown_base + half_height),
            (radius, radius, half_height),
            HIGH_VEGETATION,
            palette.CONIFER,
            density_per_m=2.2,
        )
        return
    crown_base = z + height * float(rng.uniform(0.3, 0.45))
    half_height = (z + height - crown_base) / 2
    radius = half_height * float(rng.uniform(0.8, 1.1))
    centre_z = crown_base + half_height
    b.add(
        Shape.CYLINDER,
        (x, y, (z - 0.3 + centre_z) / 2),
        (trunk_radius, trunk_radius, (centre_z - z + 0.3) / 2),
        HIGH_VEGETATION,
        palette.BARK,
    )
    density = float(rng.uniform(1.0, 1.8))
    foliage = palette.FOLIAGE.tinted(float(rng.uniform(0.85, 1.15)))
    b.add(
        Shape.ELLIPSOID,
        (x, y, centre_z),
        (radius, radius * float(rng.uniform(0.85, 1.0)), half_height),
        HIGH_VEGETATION,
        foliage,
        yaw_rad=float(rng.uniform(0, math.pi)),
        density_per_m=density,
    )
    for _ in range(int(rng.integers(1, 4))):  # irregular lobes
        angle = float(rng.uniform(0.0, 2.0 * math.pi))
        reach = radius * float(rng.uniform(0.4, 0.7))
        lobe = radius * float(rng.uniform(0.45, 0.65))
        b.add(
            Shape.ELLIPSOID,
            (
                x + reach * math.cos(angle),
                y + reach * math.sin(angle),
                centre_z + half_height * float(rng.uniform(-0.3, 0.4)),
            ),
            (lobe, lobe, lobe * 0.85),
            HIGH_VEGETATION,
            foliage,
            density_per_m=density,
        )


def bush(b: SceneBuilder, x: float, y: float, *, radius_m: float, height_m: float) -> None:
    """A porous bush (low vegetation)."""
    z = b.ground(x, y)
    b.add(
        Shape.ELLIPSOID,
        (x, y, z + 0.42 * height_m),
        (radius_m, radius_m * 0.9, height_m / 2),
        LOW_VEGETATION,
        palette.SHRUB.tinted(float(b.rng.uniform(0.85, 1.15))),
        yaw_rad=float(b.rng.uniform(0, math.pi)),
        density_per_m=3.5,
    )


def hedge(
    b: SceneBuilder, x0: float, y0: float, x1: float, y1: float, *, height_m: float = 1.4
) -> None:
    """A trimmed hedge from ``(x0, y0)`` to ``(x1, y1)``."""
    length = math.hypot(x1 - x0, y1 - y0)
    z = b.ground((x0 + x1) / 2, (y0 + y1) / 2)
    b.add(
        Shape.BOX,
        ((x0 + x1) / 2, (y0 + y1) / 2, z + height_m / 2 - 0.2),
        (length / 2, 0.4, height_m / 2 + 0.2),
        LOW_VEGETATION,
        palette.HEDGE,
        yaw_rad=math.atan2(y1 - y0, x1 - x0),
        density_per_m=4.0,
    )


def flower_bed(
    b: SceneBuilder, x: float, y: float, *, half_x_m: float, half_y_m: float, yaw_rad: float = 0.0
) -> None:
    """Flowers (low vegetation) on a bed of earth."""
    z = b.ground(x, y)
    b.zone(
        (x, y), (half_x_m + 0.3, half_y_m + 0.3), NATURAL_TERRAIN, palette.EARTH, yaw_rad=yaw_rad
    )
    b.add(
        Shape.BOX,
        (x, y, z + 0.15),
        (half_x_m, half_y_m, 0.3),
        LOW_VEGETATION,
        palette.FLOWERS,
        yaw_rad=yaw_rad,
        density_per_m=6.0,
    )
