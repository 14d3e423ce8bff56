"""``square``: a paved town square with a fountain, ringed by a road and tall buildings."""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.scene import Scene
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import (
    MAN_MADE_TERRAIN,
    NATURAL_TERRAIN,
    SceneBuilder,
    segment_distance,
)
from semantic3d.datasets.simulator.scenes.buildings import building
from semantic3d.datasets.simulator.scenes.furniture import (
    bench,
    bollard,
    fountain,
    lamp_post,
    wall,
)
from semantic3d.datasets.simulator.scenes.vegetation import bush, flower_bed, hedge, tree
from semantic3d.datasets.simulator.scenes.vehicles import car, passing_car, pedestrian
from semantic3d.datasets.simulator.terrain import Terrain

HALF_X, HALF_Y = 38.0, 30.0  # the paved square
STATIONS = ((-16.0, -12.0), (17.0, -13.0), (-2.0, 17.0))
ROAD = 8.0  # width of the ring road


def build_square(seed: int) -> Scene:
    """Build the square scene for ``seed``."""
    # A gentle bowl tilted towards the south-west.
    terrain = Terrain((0.0, 0.006, 0.004, 4.0e-5, 0.0, 3.0e-5), NATURAL_TERRAIN, palette.GRASS)
    b = SceneBuilder("square", terrain, seed=seed)
    rng = b.rng
    outer_x, outer_y = HALF_X + ROAD, HALF_Y + ROAD
    b.zone((0.0, 0.0), (outer_x + 3.0, outer_y + 3.0), MAN_MADE_TERRAIN, palette.PAVING)
    b.zone((0.0, 0.0), (outer_x, outer_y), MAN_MADE_TERRAIN, palette.ASPHALT)
    b.zone((0.0, 0.0), (HALF_X, HALF_Y), MAN_MADE_TERRAIN, palette.COBBLES)
    # A lawn with trees and bushes in the north-east quarter, a hedge around it.
    lawn_c, lawn_h = (HALF_X - 11.0, HALF_Y - 9.0), (10.0, 8.0)
    b.zone(lawn_c, lawn_h, NATURAL_TERRAIN, palette.GRASS)
    hedge(
        b,
        lawn_c[0] - lawn_h[0],
        lawn_c[1] - lawn_h[1],
        lawn_c[0] + lawn_h[0],
        lawn_c[1] - lawn_h[1],
        height_m=1.1,
    )
    hedge(
        b,
        lawn_c[0] - lawn_h[0],
        lawn_c[1] - lawn_h[1] + 4,
        lawn_c[0] - lawn_h[0],
        lawn_c[1] + lawn_h[1],
        height_m=1.1,
    )
    for _ in range(4):
        tree(b, lawn_c[0] + float(rng.uniform(-7, 7)), lawn_c[1] + float(rng.uniform(-5, 6)))
    for _ in range(6):
        bush(
            b,
            lawn_c[0] + float(rng.uniform(-8, 8)),
            lawn_c[1] + float(rng.uniform(-6, 6)),
            radius_m=float(rng.uniform(0.5, 1.3)),
            height_m=float(rng.uniform(0.7, 1.6)),
        )
    # The fountain, flower beds and benches around it, lamps and trees in pits.
    fountain(b, 0.0, 0.0, radius_m=4.5)
    for k in range(4):
        angle = k * math.pi / 2 + math.pi / 4
        flower_bed(
            b,
            9.0 * math.cos(angle),
            9.0 * math.sin(angle),
            half_x_m=2.0,
            half_y_m=0.8,
            yaw_rad=angle + math.pi / 2,
        )
        bench(
            b,
            7.0 * math.cos(angle + 0.5),
            7.0 * math.sin(angle + 0.5),
            yaw_rad=angle + 0.5 - math.pi / 2,
        )
    for x in (-28.0, -14.0, 14.0):  # (pedestrians keep clear of these, below)
        for y in (-22.0, 22.0):
            tree(b, x, y, height_m=float(rng.uniform(8, 13)), pit_radius_m=1.2)
    for x in range(-36, 37, 12):
        lamp_post(b, float(x), -HALF_Y + 0.8)
        lamp_post(b, float(x), HALF_Y - 0.8)
    for x in range(-30, 31, 3):
        bollard(b, float(x), -HALF_Y - 0.3)
    wall(b, -HALF_X + 2.0, 6.0, -HALF_X + 2.0, 16.0, height_m=0.9)
    # Buildings all round, fronts on the outer edge of the ring road.
    front_x, front_y = outer_x + 3.0, outer_y + 3.0
    x = -front_x - 10.0
    while x < front_x:
        width = float(rng.uniform(10, 18))
        depth = float(rng.uniform(10, 14))
        floors = int(rng.integers(3, 6))
        gable = bool(rng.random() < 0.5)
        building(
            b,
            x + width / 2,
            front_y + depth / 2,
            yaw_rad=0.0,
            width_m=width,
            depth_m=depth,
            floors=floors,
            gable=gable,
        )
        if abs(x + width / 2) > 12:  # a gap on the south side for the avenue
            building(
                b,
                x + width / 2,
                -front_y - depth / 2,
                yaw_rad=math.pi,
                width_m=width,
                depth_m=depth,
                floors=int(rng.integers(3, 6)),
                gable=not gable,
            )
        x += width + 0.5
    y = -front_y
    while y < front_y - 8:
        depth_along = float(rng.uniform(10, 16))
        for side in (-1.0, 1.0):
            building(
                b,
                side * (front_x + 6.5),
                y + depth_along / 2,
                yaw_rad=side * math.pi / 2,
                width_m=depth_along,
                depth_m=13.0,
                floors=int(rng.integers(3, 6)),
                gable=bool(rng.random() < 0.5),
            )
        y += depth_along + 0.5
    b.zone((0.0, -front_y - 40.0), (6.0, 40.0), MAN_MADE_TERRAIN, palette.ASPHALT)  # avenue
    # Parked cars along the ring road, traffic and pedestrians.
    for x in range(-40, 41, 5):
        if rng.random() < 0.6:
            car(b, x + float(rng.uniform(-0.3, 0.3)), outer_y - 1.2, yaw_rad=math.pi)
        if rng.random() < 0.5 and abs(x) > 10:
            car(b, x + float(rng.uniform(-0.3, 0.3)), -outer_y + 1.2, yaw_rad=0.0)
    passing_car(b, -outer_x + 4.0, HALF_Y + 3.0, outer_x - 4.0, HALF_Y + 3.0, speed_m_s=6.0)
    passing_car(b, -HALF_X - 3.5, -20.0, -HALF_X - 3.5, 20.0, speed_m_s=5.0)
    walkers = 0
    while walkers < 8:  # across the square, clear of the stations, fountain and lawn
        x0, y0 = float(rng.uniform(-34, 34)), float(rng.uniform(-26, 10))
        angle = float(rng.uniform(0, 2 * math.pi))
        length = float(rng.uniform(10, 25))
        x1, y1 = x0 + length * math.cos(angle), y0 + length * math.sin(angle)
        keep_out = [(px, py, 1.5) for px, py in STATIONS] + [(0.0, 0.0, 12.0)]
        keep_out += [(tx, ty, 1.5) for tx in (-28.0, -14.0, 14.0) for ty in (-22.0, 22.0)]
        if (
            abs(x1) < HALF_X - 2
            and -HALF_Y + 2 < y1 < 10
            and all(segment_distance(x0, y0, x1, y1, px, py) > r for px, py, r in keep_out)
        ):
            pedestrian(b, x0, y0, x1, y1, speed_m_s=float(rng.uniform(1.1, 1.6)))
            walkers += 1
    for x, y in STATIONS:
        b.station(x, y)
    return b.build()
