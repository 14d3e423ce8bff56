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

import importlib
from typing import Any

_EXPORTS = {
    "Bounds": "grid",
    "TileGrid": "grid",
    "TileKey": "grid",
    "ExtentError": "voxels",
    "compute_cells": "voxels",
    "grid_origin": "voxels",
    "pack_keys": "voxels",
    "TileData": "store",
    "TilePoints": "store",
    "TileStore": "store",
    "TileStoreWriter": "store",
    "TemporaryTileStore": "store",
    "build_tile_store": "store",
    "TileJob": "job",
    "OccupancyGrid": "occupancy",
    "open_cache_tiles": "cache_tiles",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'semantic3d.spatial' has no attribute {name!r}")
    return getattr(importlib.import_module(f"semantic3d.spatial.{module}"), name)
