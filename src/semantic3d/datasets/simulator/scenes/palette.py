"""Surfaces of the default scenes, grouped by class (base colour, reflectance, texture)."""

from __future__ import annotations

from semantic3d.datasets.simulator.primitives import Surface

# man-made terrain
ASPHALT = Surface((72, 72, 75), 0.22, 0.15, 0.8, 5.0)
PAVING = Surface((158, 148, 136), 0.45, 0.22, 0.3, 6.0)
COBBLES = Surface((128, 118, 106), 0.38, 0.35, 0.15, 8.0)
GRAVEL = Surface((150, 142, 128), 0.42, 0.3, 0.06, 12.0)
CONCRETE_GROUND = Surface((170, 168, 160), 0.5, 0.1, 1.0, 5.0)
# natural terrain
GRASS = Surface((86, 128, 52), 0.5, 0.25, 0.4, 10.0)
MEADOW = Surface((118, 138, 64), 0.48, 0.3, 0.6, 12.0)
EARTH = Surface((112, 88, 64), 0.33, 0.25, 0.25, 8.0)
# high vegetation
BARK = Surface((88, 70, 52), 0.32, 0.2, 0.2, 6.0)
FOLIAGE = Surface((52, 96, 40), 0.42, 0.3, 0.3, 14.0)
CONIFER = Surface((34, 72, 40), 0.38, 0.25, 0.3, 10.0)
# low vegetation
SHRUB = Surface((72, 112, 46), 0.45, 0.3, 0.2, 14.0)
HEDGE = Surface((46, 86, 36), 0.4, 0.2, 0.2, 10.0)
FLOWERS = Surface((176, 92, 118), 0.5, 0.6, 0.12, 28.0)
# buildings
PLASTER = Surface((214, 204, 184), 0.62, 0.08, 1.0, 5.0)
BRICK = Surface((158, 82, 62), 0.48, 0.2, 0.25, 8.0)
STONE_FACADE = Surface((176, 170, 158), 0.55, 0.15, 0.5, 6.0)
ROOF_TILES = Surface((146, 62, 46), 0.4, 0.2, 0.3, 8.0)
SLATE = Surface((72, 76, 86), 0.28, 0.15, 0.3, 6.0)
ROOF_FLAT = Surface((96, 94, 90), 0.3, 0.15, 0.8, 6.0)
GLASS = Surface((42, 52, 62), 0.08, 0.1, 0.6, 4.0)
FACADES = (PLASTER, BRICK, STONE_FACADE, PLASTER.tinted(0.92), PLASTER.tinted(1.05))
ROOFS = (ROOF_TILES, SLATE, ROOF_TILES.tinted(0.85))
# hard scape
STONE_WALL = Surface((150, 146, 136), 0.5, 0.25, 0.2, 8.0)
CONCRETE = Surface((164, 164, 158), 0.52, 0.1, 0.6, 5.0)
METAL = Surface((92, 98, 104), 0.65, 0.05, 1.0, 4.0)
WOOD = Surface((132, 96, 62), 0.45, 0.2, 0.1, 8.0)
RAIL_STEEL = Surface((108, 100, 94), 0.7, 0.1, 0.5, 5.0)
# cars
CAR_PAINTS = tuple(
    Surface(rgb, 0.6, 0.03, 1.0, 4.0)
    for rgb in (
        (178, 22, 28),
        (228, 228, 228),
        (24, 24, 28),
        (40, 62, 140),
        (150, 152, 156),
        (32, 92, 52),
        (204, 172, 44),
    )
)
TYRE = Surface((26, 26, 26), 0.1, 0.05, 1.0, 3.0)
CAR_GLASS = Surface((34, 40, 48), 0.12, 0.05, 1.0, 3.0)
# scanning artefacts (people and vehicles moving during the sweep)
CLOTHES = tuple(
    Surface(rgb, 0.4, 0.1, 0.2, 8.0)
    for rgb in ((40, 40, 60), (150, 30, 30), (200, 200, 190), (60, 90, 60), (120, 100, 70))
)
SKIN = Surface((204, 162, 130), 0.45, 0.05, 0.2, 6.0)
