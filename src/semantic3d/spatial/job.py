"""A piece of tiled work that can travel to another process: paths and numbers, never arrays.

>>> job = TileJob("/data/scan.tiles", (3, -1), (30.0, -10.0, 40.0, 0.0), halo_m=3.2)
>>> import pickle
>>> pickle.loads(pickle.dumps(job)) == job
True
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

from semantic3d.spatial.grid import Bounds, TileKey
from semantic3d.spatial.store import TileData, TileStore

__all__ = ["TileJob", "open_store"]


@dataclass(frozen=True, slots=True)
class TileJob:
    """One tile of a store, with the halo its work needs.

    Attributes:
        store: path of the tile store folder (it must be visible where the job runs).
        tile: the tile's key.
        bounds: the tile's rectangle ``(x_min, y_min, x_max, y_max)``.
        halo_m: width of the halo to read around it.
    """

    store: str
    tile: TileKey
    bounds: Bounds
    halo_m: float = 0.0

    def read(self) -> TileData:
        """The tile's core and halo, read from the store."""
        return open_store(self.store).read(self.tile, halo_m=self.halo_m)


@lru_cache(maxsize=16)
def open_store(path: str) -> TileStore:
    """The store at ``path``, opened once per process."""
    return TileStore(path)
