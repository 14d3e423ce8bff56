"""The spatially ordered copy of a binary cache: its tile store, built on first use and reused.

A cache (:mod:`semantic3d.io.cache`) keeps a scan's columns in file order, which is what
streaming readers want. Viewers, tiled models and distributed jobs want points grouped by
place: :func:`open_cache_tiles` builds the cache's :class:`~semantic3d.spatial.store.TileStore`
once, inside the cache folder (``tiles-<edge>m/``), and reopens it afterwards. The store
remembers the ``meta.json`` it was built from and is rebuilt when the cache changed.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from pathlib import Path

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.cache_meta import META_FILE
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE
from semantic3d.spatial.grid import TileGrid
from semantic3d.spatial.store import TileStore, build_tile_store

__all__ = ["DEFAULT_CACHE_TILE_SIZE_M", "open_cache_tiles"]

DEFAULT_CACHE_TILE_SIZE_M = 25.6
"""Default tile edge of a cache's tile store."""


def _fingerprint(cache: Path) -> str:
    meta = cache / META_FILE
    if not meta.is_file():
        raise DataFormatError(
            f"expected a cache folder holding {META_FILE}, found none", path=str(cache)
        )
    return hashlib.sha256(meta.read_bytes()).hexdigest()


def open_cache_tiles(
    cache: str | Path,
    *,
    tile_size_m: float = DEFAULT_CACHE_TILE_SIZE_M,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[int], None] | None = None,
) -> TileStore:
    """The tile store of the cache folder ``cache``, built on first use.

    Args:
        cache: a cache folder (``semantic3d convert scan.txt scan.cache``).
        tile_size_m: tile edge; tiles are anchored at (0, 0), so stores of several scans
            in one coordinate frame share their tiles.
        chunk_size: points streamed at a time while building.
        progress: called with the points streamed so far while building.
    """
    from semantic3d.io.cache import iter_cache

    cache = Path(cache)
    fingerprint = _fingerprint(cache)
    directory = cache / f"tiles-{tile_size_m:g}m"
    if (directory / "tiles.json").is_file():
        try:
            store = TileStore(directory)
        except DataFormatError:
            store = None
        if store is not None and store.metadata.get("source") == fingerprint:
            return store

    def chunks() -> Iterator[PointCloud]:
        done = 0
        for chunk in iter_cache(cache, chunk_size=chunk_size):
            yield chunk
            done += chunk.n_points
            if progress is not None:
                progress(done)

    return build_tile_store(
        chunks(),
        directory,
        grid=TileGrid.square(tile_size_m),
        overwrite=True,  # derived data inside the cache folder, rebuilt from it
        metadata={"source": fingerprint},
    )
