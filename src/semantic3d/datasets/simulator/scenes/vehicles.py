"""Cars and trucks (parked: class cars) and people and vehicles moving during the sweep
(class scanning artefacts: the scanner records them smeared along their path)."""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.primitives import Motion, Shape, Surface
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import CARS, SCANNING_ARTEFACTS, SceneBuilder


def car(
    b: SceneBuilder,
    x: float,
    y: float,
    *,
    yaw_rad: float,
    label: int = CARS,
    motion: Motion | None = None,
    paint: Surface | None = None,
) -> None:
    """A car heading along local +x: body, cabin and four wheels."""
    paint = (
        paint
        if paint is not None
        else palette.CAR_PAINTS[int(b.rng.integers(len(palette.CAR_PAINTS)))]
    )
    length = float(b.rng.uniform(3.9, 4.8))
    origin = (x, y, b.ground(x, y))
    half = length / 2
    b.add_local_box(
        origin, yaw_rad, (0.0, 0.0, 0.65), (half, 0.88, 0.33), label, paint, motion=motion
    )
    b.add_local_box(
        origin,
        yaw_rad,
        (-0.1 * length, 0.0, 1.22),
        (0.26 * length, 0.76, 0.25),
        label,
        palette.CAR_GLASS,
        motion=motion,
    )
    _wheels(b, origin, yaw_rad, (-half + 0.8, half - 0.8), 0.86, label, motion)


def truck(b: SceneBuilder, x: float, y: float, *, yaw_rad: float) -> None:
    """A box truck heading along local +x: cab, cargo box and wheels."""
    origin = (x, y, b.ground(x, y))
    paint = palette.CAR_PAINTS[int(b.rng.integers(len(palette.CAR_PAINTS)))]
    b.add_local_box(origin, yaw_rad, (3.3, 0.0, 1.55), (1.0, 1.2, 1.15), CARS, paint)
    b.add_local_box(
        origin, yaw_rad, (-0.9, 0.0, 2.3), (3.1, 1.25, 1.5), CARS, palette.CAR_PAINTS[1]
    )
    _wheels(b, origin, yaw_rad, (-2.8, 3.3), 1.05, CARS, None, radius=0.5)


def _wheels(
    b: SceneBuilder,
    origin: tuple[float, float, float],
    yaw_rad: float,
    axles: tuple[float, float],
    track: float,
    label: int,
    motion: Motion | None,
    *,
    radius: float = 0.33,
) -> None:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    for u in axles:
        for v in (-track, track):
            b.add(
                Shape.CYLINDER,
                (origin[0] + c * u - s * v, origin[1] + s * u + c * v, origin[2] + radius),
                (radius, radius, 0.11),
                label,
                palette.TYRE,
                yaw_rad=yaw_rad,
                roll_rad=math.pi / 2,
                motion=motion,
            )


def pedestrian(
    b: SceneBuilder,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    *,
    speed_m_s: float = 1.35,
    floor_z: float | None = None,
) -> None:
    """A person walking back and forth between two points during the sweep.

    ``floor_z`` is the height of what they walk on (the terrain at the start by default).
    """
    motion = Motion(
        (x1 - x0, y1 - y0, 0.0),
        speed_m_s,
        math.hypot(x1 - x0, y1 - y0),
        float(b.rng.uniform(0.0, 2.0 * math.hypot(x1 - x0, y1 - y0))),
    )
    z = b.ground(x0, y0) if floor_z is None else floor_z
    clothes = palette.CLOTHES[int(b.rng.integers(len(palette.CLOTHES)))]
    trousers = palette.CLOTHES[int(b.rng.integers(len(palette.CLOTHES)))]
    scale = float(b.rng.uniform(0.9, 1.08))
    b.add(
        Shape.ELLIPSOID,
        (x0, y0, z + 0.45 * scale),
        (0.16, 0.13, 0.47 * scale),
        SCANNING_ARTEFACTS,
        trousers,
        motion=motion,
    )
    b.add(
        Shape.ELLIPSOID,
        (x0, y0, z + 1.2 * scale),
        (0.22, 0.15, 0.36 * scale),
        SCANNING_ARTEFACTS,
        clothes,
        motion=motion,
    )
    b.add(
        Shape.ELLIPSOID,
        (x0, y0, z + 1.68 * scale),
        (0.1, 0.1, 0.12),
        SCANNING_ARTEFACTS,
        palette.SKIN,
        motion=motion,
    )


def passing_car(
    b: SceneBuilder, x0: float, y0: float, x1: float, y1: float, *, speed_m_s: float = 8.0
) -> None:
    """A car driving back and forth between two points during the sweep."""
    length = math.hypot(x1 - x0, y1 - y0)
    motion = Motion(
        (x1 - x0, y1 - y0, 0.0), speed_m_s, length, float(b.rng.uniform(0.0, 2.0 * length))
    )
    car(b, x0, y0, yaw_rad=math.atan2(y1 - y0, x1 - x0), label=SCANNING_ARTEFACTS, motion=motion)
