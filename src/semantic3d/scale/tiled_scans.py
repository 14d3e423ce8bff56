"""A worker's copies of the tiled scans its tasks read, opened once per process.

The client streams a scan into a :class:`~semantic3d.features.tiling.TiledScan` in a
scratch folder the workers see and sends its pickled state (paths and numbers) with each
tile task. A worker unpickles it once per scan and keeps it, with its pyramid cache and
shared levels, for the scan's next tiles. The store maps its files anew every
:data:`~semantic3d.spatial.store.REMAP_BYTES` read, so the pages of its maps do not pile up
in a long-lived worker (they count in the memory Dask limits).
"""

from __future__ import annotations

import pickle
from collections import OrderedDict

from semantic3d.features.tiling import TiledScan
from semantic3d.spatial.grid import TileKey

__all__ = ["densest_first", "open_tiled_scan"]

_KEPT_SCANS = 2
_OPEN_SCANS: OrderedDict[str, TiledScan] = OrderedDict()


def open_tiled_scan(folder: str, state: bytes) -> TiledScan:
    """This process's copy of the scan in ``folder``.

    Args:
        folder: the scan's scratch folder (the key it is kept under).
        state: the pickled :class:`TiledScan`, as the client sent it.
    """
    opened = _OPEN_SCANS.get(folder)
    if opened is None:
        # Bytes this package's client pickled for this job (a TiledScan: paths and numbers).
        opened = pickle.loads(state)
        _OPEN_SCANS[folder] = opened
        while len(_OPEN_SCANS) > _KEPT_SCANS:
            _OPEN_SCANS.popitem(last=False)
    else:
        _OPEN_SCANS.move_to_end(folder)
    return opened


def densest_first(scan: TiledScan) -> list[TileKey]:
    """Tiles by decreasing point count (the long tasks start first; ties in key order)."""
    return sorted(scan.tiles, key=lambda tile: (-scan.store.count(tile), tile))
