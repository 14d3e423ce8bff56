"""Buildings: a glazed core, facades broken by window recesses, and a gable or flat roof.

A facade is a layer ``RECESS_M`` thick made of piers (between window columns) and
spandrels (between windows of one column); the openings let rays reach the core's glass
``RECESS_M`` behind the wall, and the piers' sides form the window reveals.
"""

from __future__ import annotations

import math

from semantic3d.datasets.simulator.primitives import Shape, Surface
from semantic3d.datasets.simulator.scenes import palette
from semantic3d.datasets.simulator.scenes.builder import BUILDINGS, SceneBuilder

RECESS_M = 0.25
WINDOW_WIDTH_M = 1.2
WINDOW_HEIGHT_M = 1.45
SILL_M = 0.9
FOUNDATION_M = 0.6


def building(
    b: SceneBuilder,
    x: float,
    y: float,
    *,
    yaw_rad: float,
    width_m: float,
    depth_m: float,
    floors: int,
    gable: bool,
    floor_height_m: float = 3.0,
    facade: Surface | None = None,
    roof: Surface | None = None,
) -> None:
    """A building centred at ``(x, y)``; its front (with the door) faces local -y."""
    facade = (
        facade if facade is not None else palette.FACADES[int(b.rng.integers(len(palette.FACADES)))]
    )
    roof = roof if roof is not None else palette.ROOFS[int(b.rng.integers(len(palette.ROOFS)))]
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    corners = [
        (x + c * u - s * v, y + s * u + c * v)
        for u in (-width_m / 2, width_m / 2)
        for v in (-depth_m / 2, depth_m / 2)
    ]
    floor_z = max(b.ground(cx, cy) for cx, cy in corners) + 0.15
    base_z = min(b.ground(cx, cy) for cx, cy in corners) - FOUNDATION_M
    top_z = floor_z + floors * floor_height_m
    height = top_z - base_z
    origin = (x, y, base_z)
    # The glazed core, visible only through the window openings.
    b.add_local_box(
        origin,
        yaw_rad,
        (0.0, 0.0, height / 2),
        (width_m / 2 - RECESS_M, depth_m / 2 - RECESS_M, height / 2),
        BUILDINGS,
        palette.GLASS,
    )
    windows = [floor_z - base_z + f * floor_height_m + SILL_M for f in range(floors)]
    half_w, half_d = width_m / 2, depth_m / 2
    # (centre offset of the layer, along-axis is x?, facade length, has door)
    sides = (
        ((0.0, -half_d + RECESS_M / 2), True, width_m, True),
        ((0.0, half_d - RECESS_M / 2), True, width_m, False),
        ((-half_w + RECESS_M / 2, 0.0), False, depth_m - 2 * RECESS_M, False),
        ((half_w - RECESS_M / 2, 0.0), False, depth_m - 2 * RECESS_M, False),
    )
    for (ou, ov), along_x, length, door in sides:
        n_columns = max(1, int(length // 3.2))
        pitch = length / n_columns
        centres = [-length / 2 + (k + 0.5) * pitch for k in range(n_columns)]
        edges = [-length / 2]
        for centre in centres:
            edges += [centre - WINDOW_WIDTH_M / 2, centre + WINDOW_WIDTH_M / 2]
        edges.append(length / 2)

        def place(
            u0: float,
            u1: float,
            z0: float,
            z1: float,
            ou: float = ou,
            ov: float = ov,
            along_x: bool = along_x,
        ) -> None:
            if u1 - u0 < 1e-3 or z1 - z0 < 1e-3:
                return
            mid, half = (u0 + u1) / 2, (u1 - u0) / 2
            offset = (ou + mid, ov, (z0 + z1) / 2) if along_x else (ou, ov + mid, (z0 + z1) / 2)
            size = (
                (half, RECESS_M / 2, (z1 - z0) / 2)
                if along_x
                else (RECESS_M / 2, half, (z1 - z0) / 2)
            )
            b.add_local_box(origin, yaw_rad, offset, size, BUILDINGS, facade)

        for k in range(0, len(edges), 2):  # piers, full height
            place(edges[k], edges[k + 1], 0.0, height)
        door_column = n_columns // 2 if door else -1
        for k, centre in enumerate(centres):  # spandrels between the windows of a column
            u0, u1 = centre - WINDOW_WIDTH_M / 2, centre + WINDOW_WIDTH_M / 2
            bottoms = list(windows)
            if k == door_column:
                bottoms[0] = floor_z - base_z
            z = 0.0
            for bottom in bottoms:
                place(u0, u1, z, bottom)
                z = bottom + (2.3 if bottom < windows[0] else WINDOW_HEIGHT_M)
            place(u0, u1, z, height)
    if gable:
        overhang = 0.4
        half_depth = half_d + overhang
        rise = half_depth * math.tan(math.radians(float(b.rng.uniform(30.0, 45.0))))
        b.add_local_box(
            origin,
            yaw_rad,
            (0.0, 0.0, height + rise / 2),
            (half_w + overhang, half_depth, rise / 2),
            BUILDINGS,
            roof,
            shape=Shape.GABLE,
        )
        if b.rng.random() < 0.6:
            b.add_local_box(
                origin,
                yaw_rad,
                (half_w * 0.4, half_d * 0.3, height + rise * 0.75),
                (0.35, 0.35, rise * 0.5),
                BUILDINGS,
                palette.BRICK,
            )
    else:
        b.add_local_box(
            origin,
            yaw_rad,
            (0.0, 0.0, height + 0.1),
            (half_w, half_d, 0.1),
            BUILDINGS,
            palette.ROOF_FLAT,
        )
        for ou, ov, hu, hv in (
            (0, -half_d + 0.15, half_w, 0.15),
            (0, half_d - 0.15, half_w, 0.15),
            (-half_w + 0.15, 0, 0.15, half_d),
            (half_w - 0.15, 0, 0.15, half_d),
        ):
            b.add_local_box(
                origin, yaw_rad, (ou, ov, height + 0.5), (hu, hv, 0.3), BUILDINGS, facade
            )


def building_row(
    b: SceneBuilder,
    *,
    x_start: float,
    x_end: float,
    front_y: float,
    facing_south: bool,
    floors: tuple[int, int],
    gable_share: float,
) -> None:
    """Buildings side by side along x, fronts on the line ``y = front_y``."""
    x = x_start
    while True:
        width = float(b.rng.uniform(9.0, 17.0))
        if x + width > x_end:
            break
        depth = float(b.rng.uniform(9.0, 13.0))
        centre_y = front_y + depth / 2 if facing_south else front_y - depth / 2
        building(
            b,
            x + width / 2,
            centre_y,
            yaw_rad=0.0 if facing_south else math.pi,
            width_m=width,
            depth_m=depth,
            floors=int(b.rng.integers(floors[0], floors[1] + 1)),
            gable=bool(b.rng.random() < gable_share),
        )
        x += width + float(b.rng.choice([0.0, 0.0, 1.5, 3.0]))
