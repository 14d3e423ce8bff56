"""``village``: a crossroads with a small square, a church and houses in gardens."""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.scene import Scene
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import (
    MAN_MADE_TERRAIN,
    NATURAL_TERRAIN,
    SceneBuilder,
)
from semantic3d.datasets.simulator.scenes.buildings import building
from semantic3d.datasets.simulator.scenes.furniture import bench, fence, fountain, lamp_post, wall
from semantic3d.datasets.simulator.scenes.vegetation import bush, flower_bed, hedge, tree
from semantic3d.datasets.simulator.scenes.vehicles import car, passing_car, pedestrian
from semantic3d.datasets.simulator.terrain import Terrain

ROAD = 3.2  # half width of the roads
PATH = 4.8  # outer edge of the footpaths
FRONT_GARDEN = 6.0


def build_village(seed: int) -> Scene:
    """Build the village scene for ``seed``."""
    terrain = Terrain((0.0, 0.018, -0.006, 1.0e-5, 0.0, -3.0e-5), NATURAL_TERRAIN, palette.MEADOW)
    b = SceneBuilder("village", terrain, seed=seed)
    rng = b.rng
    for horizontal in (True, False):
        half = (140.0, PATH) if horizontal else (PATH, 140.0)
        b.zone((0.0, 0.0), half, MAN_MADE_TERRAIN, palette.PAVING)
    b.zone((0.0, 0.0), (16.0, 16.0), MAN_MADE_TERRAIN, palette.COBBLES, ellipse=True)
    for horizontal in (True, False):
        half = (140.0, ROAD) if horizontal else (ROAD, 140.0)
        b.zone((0.0, 0.0), half, MAN_MADE_TERRAIN, palette.ASPHALT)
    # The square: fountain, benches, lamps, a tree.
    fountain(b, 9.0, -9.0, radius_m=2.2)
    bench(b, 12.5, -6.0, yaw_rad=math.pi * 0.75)
    bench(b, 6.0, -12.5, yaw_rad=math.pi * 0.75)
    for x, y in ((5.0, 5.0), (-5.0, -5.0), (5.0, -5.0)):
        lamp_post(b, x, y)
    tree(b, -10.0, -10.0, height_m=14.0, pit_radius_m=1.5)
    # The church and its tower.
    building(
        b,
        -25.0,
        23.0,
        yaw_rad=0.0,
        width_m=22.0,
        depth_m=12.0,
        floors=3,
        gable=True,
        floor_height_m=3.6,
        facade=palette.STONE_FACADE,
        roof=palette.SLATE,
    )
    building(
        b,
        -11.0,
        19.5,
        yaw_rad=0.0,
        width_m=5.0,
        depth_m=5.0,
        floors=7,
        gable=True,
        facade=palette.STONE_FACADE,
        roof=palette.SLATE,
    )
    wall(b, -36.0, PATH + 0.4, -14.0, PATH + 0.4, height_m=1.0)
    # Houses in gardens along both roads.
    skip = {(-1, 1, 30.0, True), (-1, 1, 30.0, False)}
    for sx in (-1, 1):
        for sy in (-1, 1):
            for along in (30.0, 56.0, 82.0):
                for horizontal in (True, False):
                    if (sx, sy, along, horizontal) in skip:
                        continue
                    _plot(b, sx, sy, along, horizontal=horizontal)
    # Meadow trees and a row of trees along the road out of the village.
    for x in range(100, 131, 10):
        for sign in (-1.0, 1.0):
            tree(b, sign * x, 7.5 * sign, height_m=float(rng.uniform(9, 15)))
    for _ in range(12):
        x, y = (
            float(rng.uniform(-120, 120)),
            float(rng.choice([-1, 1])) * float(rng.uniform(100, 125)),
        )
        tree(b, x, y, conifer=bool(rng.random() < 0.4))
    # Traffic and walkers.
    passing_car(b, -100.0, -1.6, 100.0, -1.6, speed_m_s=8.0)
    for k in range(6):
        start = float(rng.uniform(20, 70)) * (1 if k % 2 else -1)
        if k < 3:
            pedestrian(
                b, start, 4.0 * (1 if k == 1 else -1), start + 20.0, 4.0 * (1 if k == 1 else -1)
            )
        else:
            pedestrian(
                b, 4.0 * (1 if k == 4 else -1), start, 4.0 * (1 if k == 4 else -1), start + 20.0
            )
    for x0, y0, x1, y1 in (
        (-15.0, 12.0, 0.0, 12.0),
        (8.0, 2.0, 8.0, 14.0),
        (-50.0, 4.0, -35.0, 4.0),
        (-4.0, 36.0, -4.0, 52.0),
    ):
        pedestrian(b, x0, y0, x1, y1, speed_m_s=float(rng.uniform(1.0, 1.5)))
    b.station(-7.0, 7.5)
    b.station(-42.0, 0.0)
    b.station(0.0, 44.0)
    return b.build()


def _plot(b: SceneBuilder, sx: int, sy: int, along: float, *, horizontal: bool) -> None:
    """A house with its garden on the ``(sx, sy)`` side of a road, ``along`` metres out."""
    rng = b.rng
    width, depth = float(rng.uniform(9, 13)), float(rng.uniform(8, 11))
    off = PATH + FRONT_GARDEN + depth / 2
    if horizontal:  # along the x road, front towards it
        cx, cy, yaw = sx * along, sy * off, 0.0 if sy > 0 else math.pi
    else:
        cx, cy, yaw = sx * off, sy * along, -math.pi / 2 if sx > 0 else math.pi / 2
    c, s = math.cos(yaw), math.sin(yaw)

    def world(u: float, v: float) -> tuple[float, float]:
        return cx + c * u - s * v, cy + s * u + c * v

    front = -depth / 2 - FRONT_GARDEN + 0.5  # local v of the plot's road edge
    b.zone(
        world(0.0, 1.5),
        (11.0, depth / 2 + FRONT_GARDEN + 1.0),
        NATURAL_TERRAIN,
        palette.GRASS,
        yaw_rad=yaw,
    )
    drive_u = width / 2 - 1.2 if rng.random() < 0.5 else -width / 2 + 1.2
    b.zone(
        world(drive_u + math.copysign(2.4, drive_u), (front - depth / 2) / 2),
        (1.6, (depth / 2 - front) / 2),
        MAN_MADE_TERRAIN,
        palette.GRAVEL,
        yaw_rad=yaw,
    )
    building(
        b,
        cx,
        cy,
        yaw_rad=yaw,
        width_m=width,
        depth_m=depth,
        floors=int(rng.integers(1, 3)),
        gable=True,
    )
    if rng.random() < 0.6:
        x, y = world(drive_u + math.copysign(2.4, drive_u), front + 3.2)
        car(b, x, y, yaw_rad=yaw + math.pi / 2)
    # The garden's road edge: a hedge, a fence or a low wall, leaving the drive open.
    gap_u = drive_u + math.copysign(2.4, drive_u)
    left, right = (-11.0, gap_u - 1.8) if gap_u > 0 else (gap_u + 1.8, 11.0)
    edge = rng.integers(3)
    (x0, y0), (x1, y1) = world(left, front), world(right, front)
    if edge == 0:
        hedge(b, x0, y0, x1, y1, height_m=float(rng.uniform(0.9, 1.6)))
    elif edge == 1:
        fence(b, x0, y0, x1, y1, height_m=1.2)
    else:
        wall(b, x0, y0, x1, y1, height_m=0.9)
    for _ in range(int(rng.integers(2, 5))):
        u = float(rng.uniform(-10.0, 10.0))
        v = front + float(rng.uniform(1.0, FRONT_GARDEN - 1.5))
        if abs(u - gap_u) > 2.5:
            x, y = world(u, v)
            bush(
                b,
                x,
                y,
                radius_m=float(rng.uniform(0.4, 1.0)),
                height_m=float(rng.uniform(0.6, 1.5)),
            )
    x, y = world(-gap_u * 0.2, -depth / 2 - 1.2)
    flower_bed(b, x, y, half_x_m=1.8, half_y_m=0.5, yaw_rad=yaw)
    x, y = world(float(rng.uniform(-6, 6)), depth / 2 + 5.0)
    tree(b, x, y, height_m=float(rng.uniform(5, 9)))
