"""One entry point for every point format: detect it from the path, then stream.

=============  ==========================  ==========================================
format         path                        labels
=============  ==========================  ==========================================
ASCII          ``NAME.txt`` / ``NAME.xyz``  sibling ``NAME.labels`` (read when present)
LAS / LAZ      ``.las`` / ``.laz``          ``label`` extra dimension (or ASPRS classes)
PLY            ``.ply``                     ``scalar_label`` vertex property
binary cache   a folder (``NAME.cache``)    ``labels.npy`` column
=============  ==========================  ==========================================

LAS/LAZ needs the ``las`` extra and PLY the ``ply`` extra; their modules are imported only
when such a file is used, so ASCII and caches work without them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from itertools import chain
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.ascii import COLUMNS as ASCII_COLUMNS
from semantic3d.io.ascii import iter_ascii_points, write_ascii_points
from semantic3d.io.cache import iter_cache, open_cache, write_cache
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, validate_chunk_size
from semantic3d.io.labels import attach_labels

__all__ = [
    "ASCII_SUFFIXES",
    "CACHE_SUFFIX",
    "LABELS_SUFFIX",
    "PointCountEstimate",
    "PointFormat",
    "PointsSummary",
    "describe_columns",
    "detect_format",
    "estimate_point_count",
    "iter_points",
    "read_points",
    "sibling_labels_path",
    "summarize_points",
    "write_points",
]

logger = logging.getLogger(__name__)

ASCII_SUFFIXES = (".txt", ".xyz")
CACHE_SUFFIX = ".cache"
LABELS_SUFFIX = ".labels"
_SAMPLE_BYTES = 1 << 20


class PointFormat(StrEnum):
    """The point formats this package reads and writes."""

    ASCII = "ascii"
    LAS = "las"
    LAZ = "laz"
    PLY = "ply"
    CACHE = "cache"


_BY_SUFFIX = {
    **dict.fromkeys(ASCII_SUFFIXES, PointFormat.ASCII),
    ".las": PointFormat.LAS,
    ".laz": PointFormat.LAZ,
    ".ply": PointFormat.PLY,
    CACHE_SUFFIX: PointFormat.CACHE,
}


def detect_format(path: str | Path) -> PointFormat:
    """The format of ``path``: an existing folder is a cache, otherwise the suffix decides.

    >>> detect_format("scan.txt").value, detect_format("scan.LAZ").value
    ('ascii', 'laz')
    """
    path = Path(path)
    if path.is_dir():
        return PointFormat.CACHE
    found = _BY_SUFFIX.get(path.suffix.lower())
    if found is None:
        known = ", ".join(_BY_SUFFIX)
        raise DataFormatError(
            f"expected a point file ending in one of {known} or a cache folder, "
            f"found suffix {path.suffix or '(none)'!r}",
            path=str(path),
        )
    return found


def sibling_labels_path(points_path: str | Path) -> Path | None:
    """The ``.labels`` file beside an ASCII scan (``NAME.txt`` ↔ ``NAME.labels``), if it exists."""
    candidate = Path(points_path).with_suffix(LABELS_SUFFIX)
    return candidate if candidate.is_file() else None


def iter_points(
    path: str | Path,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    labels_path: str | Path | None = None,
    sibling_labels: bool = True,
) -> Iterator[PointCloud]:
    """Stream any point file in chunks of exactly ``chunk_size`` points (the last may be shorter).

    Labels: from ``labels_path`` when given (any format; it must hold one label per
    point), otherwise from the file itself, or for ASCII from the sibling ``.labels``
    file when it exists and ``sibling_labels`` (a prediction reads none).
    """
    chunk_size = validate_chunk_size(chunk_size)
    path = Path(path)
    kind = detect_format(path)
    if kind is PointFormat.ASCII:  # labels live in a file of their own
        labels = labels_path
        if labels is None and sibling_labels:
            labels = sibling_labels_path(path)
        return iter_ascii_points(path, chunk_size=chunk_size, labels_path=labels)
    chunks = _HANDLERS[kind].read(path, chunk_size)
    if labels_path is None:
        return chunks
    return attach_labels(path, chunks, Path(labels_path), chunk_size=chunk_size)


def read_points(path: str | Path, *, labels_path: str | Path | None = None) -> PointCloud:
    """The whole file as one :class:`PointCloud` (a thin wrapper over :func:`iter_points`)."""
    chunks = list(iter_points(path, labels_path=labels_path))
    if not chunks:
        return PointCloud.empty(with_labels=labels_path is not None)
    return chunks[0] if len(chunks) == 1 else PointCloud.concatenate(chunks)


def write_points(
    path: str | Path,
    chunks: Iterable[PointCloud],
    *,
    labels_path: str | Path | None = None,
    crs: object = None,
) -> int:
    """Write point chunks in the format of ``path``'s suffix; return the number of points.

    ASCII keeps labels in a separate file: ``labels_path``, or by default the sibling
    ``NAME.labels`` when the chunks carry labels. The other formats store labels inside,
    so ``labels_path`` is rejected for them. ``crs`` (e.g. ``"EPSG:2154"``) is written
    into LAS/LAZ files and rejected for the other formats, which cannot store one.
    Nothing holds the whole cloud.
    """
    path = Path(path)
    kind = detect_format(path)
    if kind is not PointFormat.ASCII and labels_path is not None:
        raise ValueError(
            f"{path}: labels_path applies to ASCII output only; {kind.value} files store "
            "labels inside"
        )
    if crs is not None and kind not in (PointFormat.LAS, PointFormat.LAZ):
        raise ValueError(f"{path}: crs applies to LAS/LAZ output only, found {kind.value}")
    if kind is PointFormat.ASCII:
        iterator = iter(chunks)
        first = next(iterator, None)
        rest: Iterable[PointCloud] = () if first is None else chain([first], iterator)
        if labels_path is None and first is not None and first.labels is not None:
            labels_path = path.with_suffix(LABELS_SUFFIX)
        n_points = write_ascii_points(path, rest, labels_path=labels_path)
        stale = sibling_labels_path(path)
        if labels_path is None and stale is not None:
            logger.warning(
                "%s: wrote points without labels, but %s exists beside it and will be read "
                "as its labels",
                path,
                stale,
            )
        return n_points
    return _HANDLERS[kind].write(path, chunks, crs)


@dataclass(frozen=True, slots=True)
class PointCountEstimate:
    """How many points a file holds: exact from a header, estimated for ASCII."""

    n_points: int
    exact: bool


def estimate_point_count(path: str | Path) -> PointCountEstimate:
    """The number of points without reading the points (for progress bars).

    LAS/LAZ, PLY and caches record it in their headers; for ASCII it is extrapolated from
    the lines in the first MiB (exact when the file is smaller).
    """
    path = Path(path)
    return _HANDLERS[detect_format(path)].count(path)


def _count_ascii(path: Path) -> PointCountEstimate:
    size = path.stat().st_size
    with path.open("rb") as stream:
        sample = stream.read(_SAMPLE_BYTES)
    lines = sample.count(b"\n") + (1 if sample and not sample.endswith(b"\n") else 0)
    if len(sample) >= size:
        return PointCountEstimate(lines, True)
    return PointCountEstimate(round(size * lines / max(len(sample), 1)), False)


def describe_columns(path: str | Path) -> tuple[str, ...]:
    """The columns ``path`` stores, as ``name type`` strings in file order."""
    path = Path(path)
    return _HANDLERS[detect_format(path)].columns(path)


@dataclass(frozen=True, slots=True)
class PointsSummary:
    """What ``semantic3d info`` shows: counts, bounds, ranges and the label histogram.

    ``min_xyz``/``max_xyz`` and the intensity range are None for an empty file;
    ``label_counts`` (256 counts, index = label value) is None without labels.
    """

    path: Path
    format: PointFormat
    columns: tuple[str, ...]
    n_points: int
    min_xyz: NDArray[np.float64] | None
    max_xyz: NDArray[np.float64] | None
    intensity_range: tuple[int, int] | None
    label_counts: NDArray[np.int64] | None


def summarize_points(
    path: str | Path,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    labels_path: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> PointsSummary:
    """Stream ``path`` once, in constant memory, and summarise it.

    ``progress(points_done)`` is called after each chunk.
    """
    path = Path(path)
    kind = detect_format(path)
    columns = describe_columns(path)
    n_points = 0
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    intensity_low, intensity_high = np.iinfo(np.int32).max, np.iinfo(np.int32).min
    label_counts: NDArray[np.int64] | None = None
    for chunk in iter_points(path, chunk_size=chunk_size, labels_path=labels_path):
        if chunk.n_points:
            low = np.minimum(low, chunk.xyz.min(axis=0))
            high = np.maximum(high, chunk.xyz.max(axis=0))
            intensity_low = min(intensity_low, int(chunk.intensity.min()))
            intensity_high = max(intensity_high, int(chunk.intensity.max()))
        if chunk.labels is not None:
            counts = np.bincount(chunk.labels, minlength=256).astype(np.int64)
            label_counts = counts if label_counts is None else label_counts + counts
        n_points += chunk.n_points
        if progress is not None:
            progress(n_points)
    empty = n_points == 0
    return PointsSummary(
        path=path,
        format=kind,
        columns=columns,
        n_points=n_points,
        min_xyz=None if empty else low,
        max_xyz=None if empty else high,
        intensity_range=None if empty else (intensity_low, intensity_high),
        label_counts=label_counts,
    )


# -- one handler per format ----------------------------------------------------------------
# Every format-specific step is a function of the table below; the public functions above
# look a format up once. LAS/LAZ and PLY modules are imported inside their functions, so
# ASCII and caches work without the extras.


@dataclass(frozen=True, slots=True)
class _FormatHandler:
    """How one format is read, written, counted and described."""

    read: Callable[[Path, int], Iterator[PointCloud]]
    """Chunks with the labels the file itself carries (ASCII: none, see iter_points)."""
    write: Callable[[Path, Iterable[PointCloud], object], int]
    """Write chunks (the last argument is the CRS, for the formats that store one)."""
    count: Callable[[Path], PointCountEstimate]
    columns: Callable[[Path], tuple[str, ...]]


def _read_ascii(path: Path, chunk_size: int) -> Iterator[PointCloud]:
    return iter_ascii_points(path, chunk_size=chunk_size)


def _write_ascii(path: Path, chunks: Iterable[PointCloud], crs: object) -> int:
    return write_ascii_points(path, chunks)


def _columns_ascii(path: Path) -> tuple[str, ...]:
    columns = tuple(f"{name} text" for name in ASCII_COLUMNS)
    labels = sibling_labels_path(path)
    return columns + ((f"label text (in {labels.name})",) if labels else ())


def _read_cache(path: Path, chunk_size: int) -> Iterator[PointCloud]:
    return iter_cache(path, chunk_size=chunk_size)


def _write_cache(path: Path, chunks: Iterable[PointCloud], crs: object) -> int:
    return write_cache(path, chunks)


def _count_cache(path: Path) -> PointCountEstimate:
    return PointCountEstimate(open_cache(path).n_points, True)


def _columns_cache(path: Path) -> tuple[str, ...]:
    scan = open_cache(path)
    arrays: dict[str, np.ndarray] = {"xyz": scan.xyz, "intensity": scan.intensity, "rgb": scan.rgb}
    if scan.labels is not None:
        arrays["labels"] = scan.labels
    return tuple(f"{name} {a.dtype.name} {tuple(a.shape)}" for name, a in arrays.items())


def _read_ply(path: Path, chunk_size: int) -> Iterator[PointCloud]:
    from semantic3d.io.ply import iter_ply

    return iter_ply(path, chunk_size=chunk_size)


def _write_ply(path: Path, chunks: Iterable[PointCloud], crs: object) -> int:
    from semantic3d.io.ply import write_ply

    return write_ply(path, chunks)


def _count_ply(path: Path) -> PointCountEstimate:
    from semantic3d.io.ply import read_ply_header

    return PointCountEstimate(read_ply_header(path).n_vertices, True)


def _columns_ply(path: Path) -> tuple[str, ...]:
    from semantic3d.io.ply import read_ply_header

    return read_ply_header(path).vertex_properties


def _read_las(path: Path, chunk_size: int) -> Iterator[PointCloud]:
    from semantic3d.io.las import iter_las

    return iter_las(path, chunk_size=chunk_size)


def _write_las(path: Path, chunks: Iterable[PointCloud], crs: object) -> int:
    from semantic3d.io.las import write_las

    return write_las(path, chunks, crs=crs)


def _count_las(path: Path) -> PointCountEstimate:
    from semantic3d.io.las import read_las_header

    return PointCountEstimate(int(read_las_header(path).point_count), True)


def _columns_las(path: Path) -> tuple[str, ...]:
    from semantic3d.io.las import read_las_header

    point_format = read_las_header(path).point_format
    return tuple(
        f"{d.name} {d.dtype if d.dtype is not None else f'{d.num_bits}-bit'}"
        for d in point_format.dimensions
    )


_LAS = _FormatHandler(_read_las, _write_las, _count_las, _columns_las)
_HANDLERS: dict[PointFormat, _FormatHandler] = {
    PointFormat.ASCII: _FormatHandler(_read_ascii, _write_ascii, _count_ascii, _columns_ascii),
    PointFormat.LAS: _LAS,
    PointFormat.LAZ: _LAS,
    PointFormat.PLY: _FormatHandler(_read_ply, _write_ply, _count_ply, _columns_ply),
    PointFormat.CACHE: _FormatHandler(_read_cache, _write_cache, _count_cache, _columns_cache),
}
