"""Converting point files: into the binary cache once, or between any two formats.

Kept apart from :mod:`semantic3d.io.cache` (the cache format itself) because it reads
through :func:`semantic3d.io.formats.iter_points`, which itself reads caches: the format
modules import the cache, never the other way round.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.cache import (
    CachedScan,
    SourceInfo,
    is_cache_current,
    open_cache,
    open_cache_writer,
)
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE
from semantic3d.io.formats import estimate_point_count, iter_points, write_points

__all__ = ["ConvertedFile", "build_cache", "convert_file"]

logger = logging.getLogger(__name__)


def build_cache(
    points_path: str | Path,
    cache_path: str | Path,
    *,
    labels_path: str | Path | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    rebuild: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> CachedScan:
    """Convert a point file (any format :func:`semantic3d.io.formats.iter_points` reads) once.

    When ``cache_path`` already holds a cache of the same sources (name, size, mtime) it
    is opened as is, unless ``rebuild``. ``progress(done_points, total_points)`` is called
    after each chunk; ``total_points`` is exact for LAS/PLY/cache sources and an estimate
    for ASCII (corrected at the end).
    """
    points_path = Path(points_path)
    if not rebuild and is_cache_current(cache_path, points_path, labels_path=labels_path):
        logger.info("%s: cache is current, reusing it", cache_path)
        return open_cache(cache_path)
    source = SourceInfo.of(points_path)
    labels_source = None if labels_path is None else SourceInfo.of(labels_path)
    total = estimate_point_count(points_path).n_points if progress is not None else 0
    chunks = iter_points(points_path, chunk_size=chunk_size, labels_path=labels_path)
    with open_cache_writer(cache_path, source=source, labels_source=labels_source) as writer:
        for chunk in chunks:
            writer.write(chunk)
            if progress is not None:
                total = max(total, writer.n_points)
                progress(writer.n_points, total)
    if progress is not None:
        progress(writer.n_points, writer.n_points)
    logger.info("%s: cached %d points from %s", cache_path, writer.n_points, points_path)
    return open_cache(cache_path)


@dataclass(frozen=True, slots=True)
class ConvertedFile:
    """What :func:`convert_file` wrote."""

    source: Path
    destination: Path
    n_points: int
    labelled: bool
    """Whether the points carried labels (ASCII output: written to ``NAME.labels``)."""


def convert_file(
    source: str | Path,
    destination: str | Path,
    *,
    labels_path: str | Path | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    crs: object = None,
    progress: Callable[[int, int], None] | None = None,
) -> ConvertedFile:
    """Convert one point file into the format of ``destination``'s suffix, streaming.

    The output is staged under a hidden name and renamed when complete (see
    :func:`semantic3d.io.formats.write_points`); a missing output folder is created.
    ``progress(done_points, total_points)`` is called after each chunk (the total is an
    estimate for ASCII input). Same input, same bytes, in any process.
    """
    source, destination = Path(source), Path(destination)
    total = estimate_point_count(source).n_points if progress is not None else 0
    labelled = False

    def counted() -> Iterator[PointCloud]:
        nonlocal labelled, total
        done = 0
        for chunk in iter_points(source, chunk_size=chunk_size, labels_path=labels_path):
            labelled = labelled or chunk.labels is not None
            yield chunk
            done += chunk.n_points
            if progress is not None:
                total = max(total, done)
                progress(done, total)

    destination.parent.mkdir(parents=True, exist_ok=True)
    n_points = write_points(destination, counted(), crs=crs)
    if progress is not None:
        progress(n_points, n_points)
    logger.info("%s: wrote %d points from %s", destination, n_points, source)
    return ConvertedFile(source, destination, n_points, labelled)
