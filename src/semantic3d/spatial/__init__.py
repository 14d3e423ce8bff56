"""Where points are: voxel keys, tile grids, a core-plus-halo tile store, picklable tile jobs.

The layer between ``io | metrics`` and ``features | datasets | evaluation``. Everything
that cuts a scan into pieces (tiled features, label agreement, CNN crops, the labelling
viewer's level of detail, distributed work) reads its tiles from here.

- :mod:`~semantic3d.spatial.voxels`: integer cells and packed voxel keys.
- :mod:`~semantic3d.spatial.grid`: :class:`TileGrid`, square XY tiles of whole cells.
- :mod:`~semantic3d.spatial.store`: :func:`build_tile_store` spills a scan once;
  :class:`TileStore` reads any tile with a halo of any width.
- :mod:`~semantic3d.spatial.job`: :class:`TileJob`, a tile of work that pickles small.
- :mod:`~semantic3d.spatial.occupancy`: :class:`OccupancyGrid`, voxel occupancy tests.
- :mod:`~semantic3d.spatial.cache_tiles`: the tile store of a binary cache, built once.

Names are loaded on first use, so importing the package compiles nothing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.spatial.cache_tiles import open_cache_tiles
    from semantic3d.spatial.grid import Bounds, TileGrid, TileKey
    from semantic3d.spatial.job import TileJob
    from semantic3d.spatial.occupancy import OccupancyGrid
    from semantic3d.spatial.store import (
        TemporaryTileStore,
        TileData,
        TilePoints,
        TileStore,
        TileStoreWriter,
        build_tile_store,
    )
    from semantic3d.spatial.voxels import ExtentError, compute_cells, grid_origin, pack_keys

__all__ = [
    "Bounds",
    "ExtentError",
    "OccupancyGrid",
    "TemporaryTileStore",
    "TileData",
    "TileGrid",
    "TileJob",
    "TileKey",
    "TilePoints",
    "TileStore",
    "TileStoreWriter",
    "build_tile_store",
    "compute_cells",
    "grid_origin",
    "open_cache_tiles",
    "pack_keys",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "Bounds": "semantic3d.spatial.grid",
        "ExtentError": "semantic3d.spatial.voxels",
        "OccupancyGrid": "semantic3d.spatial.occupancy",
        "TemporaryTileStore": "semantic3d.spatial.store",
        "TileData": "semantic3d.spatial.store",
        "TileGrid": "semantic3d.spatial.grid",
        "TileJob": "semantic3d.spatial.job",
        "TileKey": "semantic3d.spatial.grid",
        "TilePoints": "semantic3d.spatial.store",
        "TileStore": "semantic3d.spatial.store",
        "TileStoreWriter": "semantic3d.spatial.store",
        "build_tile_store": "semantic3d.spatial.store",
        "compute_cells": "semantic3d.spatial.voxels",
        "grid_origin": "semantic3d.spatial.voxels",
        "open_cache_tiles": "semantic3d.spatial.cache_tiles",
        "pack_keys": "semantic3d.spatial.voxels",
    },
)
