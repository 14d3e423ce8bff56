"""``railway``: a double-track line with a platform, catenary, car park and embankment."""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.primitives import Motion, Shape
from semantic3d.datasets.simulator.scene import Scene
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import (
    BUILDINGS,
    HARD_SCAPE,
    MAN_MADE_TERRAIN,
    NATURAL_TERRAIN,
    SCANNING_ARTEFACTS,
    SceneBuilder,
)
from semantic3d.datasets.simulator.scenes.buildings import building
from semantic3d.datasets.simulator.scenes.furniture import bench, fence, lamp_post
from semantic3d.datasets.simulator.scenes.vegetation import bush, tree
from semantic3d.datasets.simulator.scenes.vehicles import car, pedestrian, truck
from semantic3d.datasets.simulator.terrain import Terrain

TRACKS_Y = (-2.5, 2.5)  # centre lines of the two tracks
GAUGE = 1.435
PLATFORM = (5.2, 12.0, 0.76)  # y from, y to, height above the ground
PLATFORM_X = 70.0  # half length
PARKING = (-30.0, -10.0)  # y range of the car park


def build_railway(seed: int) -> Scene:
    """Build the railway scene for ``seed``."""
    terrain = Terrain((0.0, 0.004, 0.0, 0.0, 0.0, 1.2e-4), NATURAL_TERRAIN, palette.GRASS)
    b = SceneBuilder("railway", terrain, seed=seed)
    rng = b.rng
    # Ballast bed, rails and sleepers.
    b.zone((0.0, 0.0), (150.0, 5.2), MAN_MADE_TERRAIN, palette.GRAVEL)
    for y in TRACKS_Y:
        z = b.ground(0.0, y)
        for rail in (-GAUGE / 2, GAUGE / 2):
            b.add(
                Shape.BOX,
                (0.0, y + rail, z + 0.12),
                (140.0, 0.035, 0.08),
                HARD_SCAPE,
                palette.RAIL_STEEL,
            )
        for x in range(-100, 101):
            for shift in (0.0, 0.5):
                xs = x + shift
                b.add(
                    Shape.BOX,
                    (xs, y, b.ground(xs, y) + 0.02),
                    (0.13, 1.3, 0.08),
                    HARD_SCAPE,
                    palette.CONCRETE,
                )
    # The platform (walkable: man-made terrain), its canopy and the station building.
    y0, y1, height = PLATFORM
    z = b.ground(0.0, (y0 + y1) / 2)
    b.add(
        Shape.BOX,
        (0.0, (y0 + y1) / 2, z + height / 2 - 0.5),
        (PLATFORM_X, (y1 - y0) / 2, height / 2 + 0.5),
        MAN_MADE_TERRAIN,
        palette.PAVING,
    )
    top = z + height
    b.add(Shape.BOX, (-10.0, 9.5, top + 3.4), (25.0, 2.2, 0.12), BUILDINGS, palette.ROOF_FLAT)
    for x in range(-32, 15, 8):
        b.add(
            Shape.CYLINDER, (float(x), 9.5, top + 1.7), (0.12, 0.12, 1.7), BUILDINGS, palette.METAL
        )
    building(
        b,
        20.0,
        y1 + 6.5,
        yaw_rad=0.0,
        width_m=26.0,
        depth_m=12.0,
        floors=2,
        gable=True,
        facade=palette.BRICK,
    )
    for bench_x in (-44.0, -28.0, 30.0):
        bench(b, bench_x, 10.5, yaw_rad=0.0)
    for x in range(-60, 61, 20):
        lamp_post(b, float(x), 11.3)
    # Catenary: masts, cantilevers and contact wires.
    for x in range(-100, 101, 50):
        mast_x = float(x)
        z = b.ground(mast_x, -6.3)
        b.add(Shape.BOX, (mast_x, -6.3, z + 3.5), (0.15, 0.15, 3.9), HARD_SCAPE, palette.METAL)
        b.add(Shape.BOX, (mast_x, -1.6, z + 6.6), (0.05, 4.7, 0.05), HARD_SCAPE, palette.METAL)
    for y in TRACKS_Y:
        z = b.ground(0.0, y)
        b.add(
            Shape.CYLINDER,
            (0.0, y, z + 5.6),
            (0.012, 0.012, 120.0),
            HARD_SCAPE,
            palette.METAL,
            pitch_rad=math.pi / 2,
        )
    # Car park south of the line behind a fence, with a hedge of bushes.
    p0, p1 = PARKING
    b.zone((0.0, (p0 + p1) / 2), (60.0, (p1 - p0) / 2), MAN_MADE_TERRAIN, palette.ASPHALT)
    b.zone((0.0, -8.0), (60.0, 2.0), MAN_MADE_TERRAIN, palette.PAVING)
    fence(b, -100.0, -6.9, 100.0, -6.9, height_m=1.8)
    for x in range(-54, 55, 3):
        for y, yaw in ((p1 - 3.0, math.pi / 2), (p0 + 3.0, -math.pi / 2)):
            if rng.random() < 0.6 and abs(x) > 3:
                car(b, float(x), y, yaw_rad=yaw)
    truck(b, 52.0, -20.0, yaw_rad=math.pi)
    for x in range(-56, 57, 8):
        bush(
            b,
            float(x) + float(rng.uniform(-1, 1)),
            p0 - 1.5,
            radius_m=float(rng.uniform(0.8, 1.4)),
            height_m=float(rng.uniform(1.0, 1.9)),
        )
    # Embankment north of the station: earth mounds, trees and bushes.
    for _ in range(6):
        mx, my = float(rng.uniform(-120, 120)), float(rng.uniform(28, 45))
        b.add(
            Shape.ELLIPSOID,
            (mx, my, b.ground(mx, my) - 2.0),
            (float(rng.uniform(8, 16)), float(rng.uniform(5, 9)), 3.5),
            NATURAL_TERRAIN,
            palette.EARTH,
        )
    for _ in range(18):
        tx, ty = float(rng.uniform(-120, 120)), float(rng.uniform(24, 60))
        tree(b, tx, ty, conifer=bool(rng.random() < 0.3))
    for _ in range(14):
        bx, by = float(rng.uniform(-100, 100)), float(rng.uniform(20, 40))
        bush(
            b, bx, by, radius_m=float(rng.uniform(0.6, 1.5)), height_m=float(rng.uniform(0.7, 1.8))
        )
    for x in range(-120, 121, 12):
        tree(b, float(x) + float(rng.uniform(-2, 2)), p0 - 8.0 + float(rng.uniform(-2, 2)))
    # A slow train passing on the far track; travellers on the platform.
    motion = Motion((1.0, 0.0, 0.0), 6.0, 140.0, float(rng.uniform(0, 280)))
    z = b.ground(0.0, TRACKS_Y[0])
    for k in range(3):
        b.add(
            Shape.BOX,
            (-150.0 + k * 21.0, TRACKS_Y[0], z + 2.3),
            (10.2, 1.45, 1.9),
            SCANNING_ARTEFACTS,
            palette.CAR_PAINTS[3],
            motion=motion,
        )
    for _ in range(5):
        x0 = float(rng.uniform(-60, 40))
        y = float(rng.uniform(6.3, 8.3))
        pedestrian(b, x0, y, x0 + float(rng.uniform(10, 25)), y, floor_z=top)
    for _ in range(2):
        x0 = float(rng.uniform(-50, 20))
        pedestrian(b, x0, -8.5, x0 + 20.0, -8.5)
    b.station(-52.0, 9.9, floor_z=top)
    b.station(8.0, -20.0)
    b.station(40.0, 9.9, floor_z=top)
    return b.build()
