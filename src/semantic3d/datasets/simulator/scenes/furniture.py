"""Hard scape: garden walls, fences, benches, poles, bollards, fountains."""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.primitives import Shape
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import HARD_SCAPE, SceneBuilder


def wall(
    b: SceneBuilder, x0: float, y0: float, x1: float, y1: float, *, height_m: float = 1.2
) -> None:
    """A garden wall from ``(x0, y0)`` to ``(x1, y1)``."""
    length = math.hypot(x1 - x0, y1 - y0)
    z = min(b.ground(x0, y0), b.ground(x1, y1))
    b.add(
        Shape.BOX,
        ((x0 + x1) / 2, (y0 + y1) / 2, z + height_m / 2 - 0.2),
        (length / 2, 0.2, height_m / 2 + 0.2),
        HARD_SCAPE,
        palette.STONE_WALL,
        yaw_rad=math.atan2(y1 - y0, x1 - x0),
    )


def fence(
    b: SceneBuilder, x0: float, y0: float, x1: float, y1: float, *, height_m: float = 1.5
) -> None:
    """Posts every 2.5 m joined by two rails."""
    length = math.hypot(x1 - x0, y1 - y0)
    yaw = math.atan2(y1 - y0, x1 - x0)
    n_posts = max(2, int(length // 2.5) + 1)
    for k in range(n_posts):
        f = k / (n_posts - 1)
        x, y = x0 + f * (x1 - x0), y0 + f * (y1 - y0)
        z = b.ground(x, y)
        b.add(
            Shape.BOX,
            (x, y, z + height_m / 2 - 0.2),
            (0.05, 0.05, height_m / 2 + 0.2),
            HARD_SCAPE,
            palette.METAL,
            yaw_rad=yaw,
        )
    z = b.ground((x0 + x1) / 2, (y0 + y1) / 2)
    for rail_z in (0.35, height_m - 0.1):
        b.add(
            Shape.BOX,
            ((x0 + x1) / 2, (y0 + y1) / 2, z + rail_z),
            (length / 2, 0.025, 0.04),
            HARD_SCAPE,
            palette.METAL,
            yaw_rad=yaw,
        )


def bench(b: SceneBuilder, x: float, y: float, *, yaw_rad: float) -> None:
    """A park bench facing local -y."""
    origin = (x, y, b.ground(x, y))
    b.add_local_box(origin, yaw_rad, (0.0, 0.0, 0.45), (0.9, 0.22, 0.03), HARD_SCAPE, palette.WOOD)
    b.add_local_box(origin, yaw_rad, (0.0, 0.22, 0.7), (0.9, 0.03, 0.2), HARD_SCAPE, palette.WOOD)
    for u in (-0.75, 0.75):
        b.add_local_box(
            origin, yaw_rad, (u, 0.0, 0.1), (0.04, 0.2, 0.32), HARD_SCAPE, palette.METAL
        )


def lamp_post(b: SceneBuilder, x: float, y: float, *, height_m: float = 5.0) -> None:
    """A lamp post: a thin pole and a lantern."""
    z = b.ground(x, y)
    b.add(
        Shape.CYLINDER,
        (x, y, z + height_m / 2 - 0.2),
        (0.07, 0.07, height_m / 2 + 0.2),
        HARD_SCAPE,
        palette.METAL,
    )
    b.add(
        Shape.ELLIPSOID, (x, y, z + height_m + 0.15), (0.25, 0.25, 0.22), HARD_SCAPE, palette.METAL
    )


def bollard(b: SceneBuilder, x: float, y: float) -> None:
    """A short concrete post."""
    z = b.ground(x, y)
    b.add(Shape.CYLINDER, (x, y, z + 0.3), (0.12, 0.12, 0.6), HARD_SCAPE, palette.CONCRETE)


def fountain(b: SceneBuilder, x: float, y: float, *, radius_m: float) -> None:
    """A round basin with a central column and bowl."""
    z = b.ground(x, y)
    b.add(
        Shape.CYLINDER, (x, y, z + 0.2), (radius_m, radius_m, 0.45), HARD_SCAPE, palette.STONE_WALL
    )
    b.add(Shape.CYLINDER, (x, y, z + 1.3), (0.3, 0.3, 0.7), HARD_SCAPE, palette.STONE_WALL)
    b.add(
        Shape.CYLINDER,
        (x, y, z + 2.05),
        (radius_m * 0.35, radius_m * 0.35, 0.12),
        HARD_SCAPE,
        palette.STONE_WALL,
    )
