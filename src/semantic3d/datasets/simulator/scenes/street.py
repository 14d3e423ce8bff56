"""``street``: a straight town street with terraced houses, a pocket park and a side street."""

from __future__ import annotations

from semantic3d.datasets.simulator.scene import Scene
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import (
    MAN_MADE_TERRAIN,
    NATURAL_TERRAIN,
    SceneBuilder,
)
from semantic3d.datasets.simulator.scenes.buildings import building_row
from semantic3d.datasets.simulator.scenes.furniture import bench, bollard, fence, lamp_post, wall
from semantic3d.datasets.simulator.scenes.vegetation import bush, flower_bed, hedge, tree
from semantic3d.datasets.simulator.scenes.vehicles import car, passing_car, pedestrian, truck
from semantic3d.datasets.simulator.terrain import Terrain

ROAD_HALF_WIDTH = 4.0
FRONT = 9.0  # facades on y = ±FRONT
PARK = (-58.0, -32.0)  # x range of the pocket park (north side)
SIDE_STREET = (16.0, 26.0)  # x range of the side street (south side)


def build_street(seed: int) -> Scene:
    """Build the street scene for ``seed``."""
    terrain = Terrain((0.0, 0.012, 0.0, 0.0, 0.0, -2.0e-5), NATURAL_TERRAIN, palette.GRASS)
    b = SceneBuilder("street", terrain, seed=seed)
    rng = b.rng
    b.zone((0.0, 0.0), (140.0, ROAD_HALF_WIDTH), MAN_MADE_TERRAIN, palette.ASPHALT)
    for side in (-1.0, 1.0):
        b.zone(
            (0.0, side * (ROAD_HALF_WIDTH + FRONT) / 2),
            (140.0, (FRONT - ROAD_HALF_WIDTH) / 2),
            MAN_MADE_TERRAIN,
            palette.PAVING,
        )
    b.zone(
        ((SIDE_STREET[0] + SIDE_STREET[1]) / 2, -40.0),
        (3.5, 31.0),
        MAN_MADE_TERRAIN,
        palette.ASPHALT,
    )
    b.zone((-110.0, -40.0), (30.0, 20.0), MAN_MADE_TERRAIN, palette.GRAVEL)  # a yard behind
    # Terraced houses on both sides, leaving room for the park and the side street.
    building_row(
        b,
        x_start=-125.0,
        x_end=PARK[0],
        front_y=FRONT,
        facing_south=True,
        floors=(2, 4),
        gable_share=0.6,
    )
    building_row(
        b,
        x_start=PARK[1],
        x_end=125.0,
        front_y=FRONT,
        facing_south=True,
        floors=(2, 4),
        gable_share=0.6,
    )
    building_row(
        b,
        x_start=-125.0,
        x_end=SIDE_STREET[0] - 3.0,
        front_y=-FRONT,
        facing_south=False,
        floors=(2, 4),
        gable_share=0.6,
    )
    building_row(
        b,
        x_start=SIDE_STREET[1] + 3.0,
        x_end=125.0,
        front_y=-FRONT,
        facing_south=False,
        floors=(2, 4),
        gable_share=0.6,
    )
    # Pocket park: lawn (the base terrain), trees, bushes, flowers, benches, a fence.
    px0, px1 = PARK
    fence(b, px0 + 0.5, FRONT + 0.3, -47.0, FRONT + 0.3)
    fence(b, -43.0, FRONT + 0.3, px1 - 0.5, FRONT + 0.3)
    b.zone((-45.0, FRONT + 10.0), (1.5, 10.0), MAN_MADE_TERRAIN, palette.GRAVEL)  # park path
    for _ in range(5):
        tree(b, float(rng.uniform(px0 + 3, px1 - 3)), float(rng.uniform(FRONT + 6, FRONT + 28)))
    for _ in range(6):
        bush(
            b,
            float(rng.uniform(px0 + 2, px1 - 2)),
            float(rng.uniform(FRONT + 3, FRONT + 25)),
            radius_m=float(rng.uniform(0.6, 1.4)),
            height_m=float(rng.uniform(0.8, 1.8)),
        )
    flower_bed(b, -52.0, FRONT + 4.0, half_x_m=3.0, half_y_m=1.0)
    flower_bed(b, -38.0, FRONT + 4.0, half_x_m=3.0, half_y_m=1.0)
    bench(b, -47.5, FRONT + 12.0, yaw_rad=-1.5708)
    bench(b, -42.5, FRONT + 12.0, yaw_rad=1.5708)
    hedge(b, px0 + 0.5, FRONT + 30.0, px1 - 0.5, FRONT + 30.0)
    # Street furniture and trees along the pavements.
    for side in (-1.0, 1.0):
        for x in range(-110, 111, 14):
            if side < 0 and SIDE_STREET[0] - 2 < x < SIDE_STREET[1] + 2:
                continue
            tree(
                b,
                x + float(rng.uniform(-1, 1)),
                side * (FRONT - 1.6),
                height_m=float(rng.uniform(7, 12)),
                pit_radius_m=0.9,
            )
        for x in range(-105, 106, 25):
            lamp_post(b, float(x), side * (ROAD_HALF_WIDTH + 0.5))
        for x in range(-103, 104, 14):  # flower beds along the facades, between the trees
            if (
                not (side < 0 and SIDE_STREET[0] - 5 < x < SIDE_STREET[1] + 5)
                and rng.random() < 0.7
            ):
                flower_bed(b, float(x), side * (FRONT - 0.6), half_x_m=2.0, half_y_m=0.35)
        for x in range(-100, 101, 5):
            if side < 0 and abs(x - 48) < 9:
                continue
            if rng.random() < 0.55 and abs(x) > 4:
                car(
                    b,
                    x + float(rng.uniform(-0.4, 0.4)),
                    side * (ROAD_HALF_WIDTH - 0.5),
                    yaw_rad=0.0 if side < 0 else 3.1416,
                )
    truck(b, 48.0, -(ROAD_HALF_WIDTH - 0.2), yaw_rad=0.0)
    for bollard_x in (12.0, 14.0, 28.0, 30.0):
        bollard(b, bollard_x, -ROAD_HALF_WIDTH - 0.6)
    wall(b, SIDE_STREET[0] - 2.8, -FRONT, SIDE_STREET[0] - 2.8, -FRONT - 25.0, height_m=2.0)
    wall(b, SIDE_STREET[1] + 2.8, -FRONT, SIDE_STREET[1] + 2.8, -FRONT - 25.0, height_m=1.2)
    # Traffic and pedestrians moving while the scanner turns.
    passing_car(b, -90.0, 1.5, 90.0, 1.5, speed_m_s=9.0)
    passing_car(b, 90.0, -1.5, -90.0, -1.5, speed_m_s=7.0)
    for k in range(6):
        side = 1.0 if k % 2 else -1.0
        x0 = float(rng.uniform(-60, 40))
        pedestrian(b, x0, side * 5.6, x0 + float(rng.uniform(15, 30)), side * 5.6)
    b.station(-22.0, 0.0)
    b.station(6.0, 0.0)
    b.station(34.0, 0.0)
    return b.build()
