"""The binary cache: a scan converted once into memory-mapped column files.

Parsing a 17 GB ASCII scan takes minutes; reopening its cache takes microseconds and
reads only the pages that are touched. A cache is a folder::

    scan.cache/
      meta.json        format name and version, n_points, columns, source file identity
      xyz.npy          (n, 3) float64 metres
      intensity.npy    (n,) int32
      rgb.npy          (n, 3) uint8
      labels.npy       (n,) uint8, only when the scan has labels

Columns are ``.npy`` files, so any numpy (``np.load(path, mmap_mode="r")``) can read them
without this package. :func:`open_cache` validates ``meta.json`` against every column
(dtype, shape, byte size) and raises :class:`~semantic3d.core.errors.DataFormatError` on
a truncated or corrupt cache; it never reads the data itself.

Writing streams: each chunk is appended to the column files, whose ``.npy`` headers are
rewritten with the final shape on close. Everything is written into a hidden temporary
folder beside the destination and renamed into place at the end, so a cache folder is
either complete or absent (an existing cache is replaced only once the new one is
complete).
"""

from __future__ import annotations

import io
import json
import logging
import shutil
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.cache_meta import (
    CACHE_FORMAT,
    CACHE_FORMAT_VERSION,
    COLUMNS,
    META_FILE,
    CacheMeta,
    SourceInfo,
)
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, validate_chunk_size
from semantic3d.io.staging import StagedWriter, write_chunks

__all__ = [
    "CACHE_FORMAT",
    "CACHE_FORMAT_VERSION",
    "META_FILE",
    "CacheMeta",
    "CacheWriter",
    "CachedScan",
    "SourceInfo",
    "is_cache",
    "is_cache_current",
    "iter_cache",
    "open_cache",
    "open_cache_writer",
    "read_cache",
    "write_cache",
]

logger = logging.getLogger(__name__)

_NPY_HEADER_BYTES = 128


@dataclass(frozen=True, slots=True)
class CachedScan:
    """An opened cache: read-only memory maps of every column, opened in O(1).

    ``cloud`` views the whole scan as a :class:`PointCloud` without reading it; slicing it
    (``scan.cloud[a:b]``) reads only those points.
    """

    path: Path
    meta: CacheMeta
    xyz: NDArray[np.float64]
    intensity: NDArray[np.int32]
    rgb: NDArray[np.uint8]
    labels: NDArray[np.uint8] | None

    @property
    def n_points(self) -> int:
        """Number of points."""
        return self.meta.n_points

    @property
    def cloud(self) -> PointCloud:
        """The scan as a read-only :class:`PointCloud` over the memory maps (no copy)."""
        return PointCloud(self.xyz, self.intensity, self.rgb, self.labels)


def is_cache(path: str | Path) -> bool:
    """True when ``path`` is a folder holding a ``meta.json`` (a cache, maybe corrupt)."""
    return (Path(path) / META_FILE).is_file()


def open_cache(path: str | Path) -> CachedScan:
    """Open the cache folder ``path``, validating it, without reading the points.

    Raises:
        DataFormatError: not a cache, an unknown format version, or a column file that is
            missing, truncated or disagrees with ``meta.json``.
    """
    path = Path(path)
    meta_path = path / META_FILE
    if not meta_path.is_file():
        raise DataFormatError(
            f"expected a cache folder holding {META_FILE}, found none", path=str(path)
        )
    try:
        data = json.loads(meta_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(
            f"expected JSON, found corrupt text: {exc}", path=str(meta_path)
        ) from exc
    meta = CacheMeta.from_dict(data, path=str(meta_path))
    columns = {
        name: _open_column(path / f"{name}.npy", meta.n_points, dtype, tail)
        for name, (dtype, tail) in COLUMNS.items()
        if name != "labels" or meta.has_labels
    }
    return CachedScan(
        path, meta, columns["xyz"], columns["intensity"], columns["rgb"], columns.get("labels")
    )


def iter_cache(path: str | Path, *, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Iterator[PointCloud]:
    """Stream a cache in chunks of exactly ``chunk_size`` points (the last may be shorter).

    Chunks are in-memory copies, independent of the files. They are read with plain
    sequential reads, not through the memory maps: touched mapped pages count in the
    process's resident memory, and streaming a 17 GB scan should not look like using it.
    """
    chunk_size = validate_chunk_size(chunk_size)
    scan = open_cache(path)  # validates every column before the first chunk
    return _iter_scan(scan, chunk_size)


def _iter_scan(scan: CachedScan, chunk_size: int) -> Iterator[PointCloud]:
    names = [name for name in COLUMNS if name != "labels" or scan.meta.has_labels]
    streams = {name: (scan.path / f"{name}.npy").open("rb") for name in names}
    try:
        for name, stream in streams.items():
            stream.seek(_data_offset(getattr(scan, name)))
        for start in range(0, scan.n_points, chunk_size):
            n = min(chunk_size, scan.n_points - start)
            columns = {name: _read_rows(stream, name, n) for name, stream in streams.items()}
            yield PointCloud(
                columns["xyz"], columns["intensity"], columns["rgb"], columns.get("labels")
            )
    finally:
        for stream in streams.values():
            stream.close()


def _read_rows(stream: io.BufferedReader, name: str, n: int) -> np.ndarray:
    dtype, tail = COLUMNS[name]
    array = np.empty((n, *tail), dtype=dtype)
    n_read = stream.readinto(array.data)
    if n_read != array.nbytes:
        raise DataFormatError(
            f"expected {array.nbytes} more bytes, found {n_read}: the column shrank while read",
            path=stream.name,
        )
    return array


def _data_offset(column: np.ndarray) -> int:
    """Where the data of a column opened by :func:`_open_column` starts in its file."""
    return int(column.offset) if isinstance(column, np.memmap) else _NPY_HEADER_BYTES


def read_cache(path: str | Path) -> PointCloud:
    """The whole cache as one in-memory :class:`PointCloud`."""
    scan = open_cache(path)
    return next(
        _iter_scan(scan, max(scan.n_points, 1)), PointCloud.empty(with_labels=scan.meta.has_labels)
    )


class CacheWriter(StagedWriter):
    """Appends point chunks to a new cache; the folder appears, complete, on close.

    The first chunk decides whether a labels column exists; every later chunk must
    match. On an exception inside the ``with`` block nothing is left behind (an existing
    cache at ``path`` stays as it was).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        source: SourceInfo | None = None,
        labels_source: SourceInfo | None = None,
    ) -> None:
        self.path = Path(path)
        self.n_points = 0
        self.source = source
        self.labels_source = labels_source
        if self.path.exists() and not _replaceable(self.path):
            raise DataFormatError(
                "expected a new path, an empty folder or a cache to replace, found an "
                "existing file or folder that is not a cache",
                path=str(self.path),
            )
        self._staging = self.path.parent / f".{self.path.name}.partial-{uuid.uuid4().hex[:12]}"
        self._staging.mkdir(parents=False)
        self._has_labels: bool | None = None
        self._streams: dict[str, BinaryIO] = {}

    def write(self, cloud: PointCloud) -> None:
        """Append ``cloud``."""
        if self._has_labels is None:
            self._start(cloud.labels is not None)
        self.check_labels(cloud, bool(self._has_labels))
        arrays = {"xyz": cloud.xyz, "intensity": cloud.intensity, "rgb": cloud.rgb}
        if cloud.labels is not None:
            arrays["labels"] = cloud.labels
        for name, array in arrays.items():
            dtype = COLUMNS[name][0]
            self._streams[name].write(np.ascontiguousarray(array, dtype=dtype).data)
        self.n_points += cloud.n_points

    def _start(self, has_labels: bool) -> None:
        self._has_labels = has_labels
        for name, (dtype, tail) in COLUMNS.items():
            if name == "labels" and not has_labels:
                continue
            stream = (self._staging / f"{name}.npy").open("wb")
            stream.write(_npy_header(dtype, (0, *tail)))
            self._streams[name] = stream

    def close(self) -> None:
        """Finish the column headers, write ``meta.json`` and move the cache into place."""
        if self._has_labels is None:
            self._start(False)
        for name, stream in self._streams.items():
            dtype, tail = COLUMNS[name]
            stream.seek(0)
            stream.write(_npy_header(dtype, (self.n_points, *tail)))
            stream.close()
        meta = CacheMeta(self.n_points, bool(self._has_labels), self.source, self.labels_source)
        (self._staging / META_FILE).write_text(
            json.dumps(meta.to_dict(), indent=2) + "\n", encoding="utf-8"
        )
        _replace_folder(self._staging, self.path)

    def abort(self) -> None:
        """Drop everything written so far."""
        for stream in self._streams.values():
            stream.close()
        shutil.rmtree(self._staging, ignore_errors=True)


def open_cache_writer(
    path: str | Path,
    *,
    source: SourceInfo | None = None,
    labels_source: SourceInfo | None = None,
) -> CacheWriter:
    """Open a :class:`CacheWriter`; use it as a context manager."""
    return CacheWriter(path, source=source, labels_source=labels_source)


def write_cache(
    path: str | Path,
    chunks: Iterable[PointCloud],
    *,
    source: SourceInfo | None = None,
    labels_source: SourceInfo | None = None,
) -> int:
    """Write point chunks as a cache folder, streaming; return the number of points."""
    return write_chunks(open_cache_writer(path, source=source, labels_source=labels_source), chunks)


def is_cache_current(
    cache_path: str | Path, points_path: str | Path, *, labels_path: str | Path | None = None
) -> bool:
    """True when ``cache_path`` is a valid cache built from these exact source files.

    Sources are compared by name, size and modification time.
    """
    try:
        meta = open_cache(cache_path).meta
    except (DataFormatError, OSError):
        return False
    labels = None if labels_path is None else SourceInfo.of(labels_path)
    return meta.source == SourceInfo.of(points_path) and meta.labels_source == labels


def _open_column(path: Path, n_points: int, dtype: np.dtype, tail: tuple[int, ...]) -> np.ndarray:
    shape = (n_points, *tail)
    if not path.is_file():
        raise DataFormatError(
            f"expected column file {path.name}, found none", path=str(path.parent)
        )
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DataFormatError(
            f"expected a .npy column of shape {shape}, found an unreadable or truncated "
            f"file ({exc})",
            path=str(path),
        ) from exc
    if array.shape != shape or array.dtype != dtype:
        raise DataFormatError(
            f"expected shape {shape} {dtype}, found {array.shape} {array.dtype}",
            path=str(path),
        )
    expected_size = array.offset + array.nbytes if isinstance(array, np.memmap) else None
    if expected_size is not None and path.stat().st_size != expected_size:
        raise DataFormatError(
            f"expected {expected_size} bytes, found {path.stat().st_size}: corrupt column",
            path=str(path),
        )
    return array


def _npy_header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
    """A ``.npy`` version 1.0 header padded to a fixed size, so it can be rewritten in place."""
    # numpy has no appending .npy writer: the header holds the final shape, so it is
    # written once with a provisional shape and again, same length, on close.
    text = repr(
        {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
    )
    room = _NPY_HEADER_BYTES - len(np.lib.format.MAGIC_PREFIX) - 2 - 2
    body = text.ljust(room - 1).encode("latin1") + b"\n"
    if len(body) != room:
        raise ValueError(f"shape {shape} does not fit a {_NPY_HEADER_BYTES}-byte .npy header")
    return np.lib.format.MAGIC_PREFIX + b"\x01\x00" + len(body).to_bytes(2, "little") + body


def _replace_folder(staging: Path, destination: Path) -> None:
    """Move ``staging`` to ``destination``, replacing a previous cache there."""
    if not destination.exists():
        staging.rename(destination)
        return
    retired = destination.parent / f".{destination.name}.old-{uuid.uuid4().hex[:12]}"
    destination.rename(retired)
    try:
        staging.rename(destination)
    except OSError:
        retired.rename(destination)
        raise
    shutil.rmtree(retired, ignore_errors=True)


def _replaceable(path: Path) -> bool:
    """A path a cache may be written to: a previous cache or an empty folder."""
    return path.is_dir() and (is_cache(path) or not any(path.iterdir()))
