"""LAS and LAZ point files through laspy (LAZ through its lazrs backend), streamed in chunks.

Files written here are LAS 1.4, point format 7 (x y z, 16-bit intensity and RGB, 8-bit
classification), with the WKT bit of the global encoding set (LAS 1.4 requires it for
point formats 6-10) and, when a ``crs`` is given (``EPSG:2154``, any definition pyproj
reads; the ``las`` extra installs pyproj), an OGC WKT coordinate-system record. They
carry two extra-bytes dimensions so that nothing is lost:

- ``semantic3d_intensity`` (int32): the exact signed intensity (Semantic3D files hold
  values such as ``-1515``). The standard uint16 ``intensity`` field gets
  ``clip(value + 2048, 0, 65535)`` (:data:`INTENSITY_OFFSET`) so other software sees an
  ordered, non-negative intensity; the benchmark's range -2048..2047 maps to 0..4095.
  The shift is kept on purpose (without it every negative intensity would clip to 0);
  readers of this package take the exact value from ``semantic3d_intensity``.
- ``label`` (uint8, only when the chunks carry labels): the exact label value. The
  standard ``classification`` field gets the ASPRS code of :data:`ASPRS_BY_LABEL`.

Coordinates are stored as int32 millimetres (scale 0.001) from an offset taken from the
first non-empty chunk: the floor of its minimum, in whole metres. LAS header offsets
cannot change once points are streamed, so every point must lie within ±2^31 mm
(±2147 km) of that offset; a point further away raises
:class:`~semantic3d.core.errors.DataFormatError` instead of wrapping around. Georeferenced
coordinates (x ≈ 870 000 m) keep their millimetres.

Colours are 8-bit in a :class:`~semantic3d.core.PointCloud` and 16-bit in LAS: written as
``value * 257`` (0..255 → 0..65535) and read back as ``value >> 8``. Files from other
software that store 8-bit values in the 16-bit fields are recognised on the first chunk
with a non-zero colour (every value ≤ 255) and read unshifted.

Reading a file without the extra dimensions (written by other software): intensity is
the uint16 field as is; labels come from the classification through
:data:`LABEL_BY_ASPRS` (codes without an unambiguous Semantic3D class give 0), or are
left out with ``map_classification=False``. A file with ``semantic3d_intensity`` but no
``label`` dimension was written here from points without labels: it reads back without
labels. See ``docs/formats.md`` for the tables and their reasons.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import suppress
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.core.errors import DataFormatError, MissingExtraError, Semantic3DError, require
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, validate_chunk_size
from semantic3d.io.staging import StagedPath, StagedWriter, write_chunks

try:
    import laspy
except ImportError as _exc:  # pragma: no cover - exercised only without the extra
    raise MissingExtraError("laspy", "las") from _exc

__all__ = [
    "ASPRS_BY_LABEL",
    "COORDINATE_SCALE_M",
    "INTENSITY_DIMENSION",
    "INTENSITY_OFFSET",
    "LABEL_BY_ASPRS",
    "LABEL_DIMENSION",
    "CrsError",
    "LasPointWriter",
    "iter_las",
    "open_las_writer",
    "parse_crs",
    "read_las",
    "read_las_header",
    "write_las",
]

LABEL_DIMENSION = "label"
"""Extra-bytes dimension (uint8) holding the exact Semantic3D label value."""

INTENSITY_DIMENSION = "semantic3d_intensity"
"""Extra-bytes dimension (int32) holding the exact signed intensity."""

INTENSITY_OFFSET = 2048
"""Added to the signed intensity (then clipped to 0..65535) for the standard uint16 field."""

COORDINATE_SCALE_M = 0.001
"""LAS integer coordinate unit in metres: millimetres."""

POINT_FORMAT = 7
LAS_VERSION = "1.4"

ASPRS_BY_LABEL: NDArray[np.uint8] = np.ones(256, dtype=np.uint8)
"""ASPRS LAS 1.4 classification code written for each label value (index = label value).

0 unlabelled → 1 unclassified, 1 man-made terrain → 11 road surface, 2 natural terrain →
2 ground, 3 high vegetation → 5, 4 low vegetation → 3, 5 buildings → 6 building,
6 hard scape → 64 and 8 cars → 65 (no standard class; 64..255 are user-definable),
7 scanning artefacts → 7 low point (noise). Values above 8 → 1 unclassified.
"""
ASPRS_BY_LABEL[:9] = (1, 11, 2, 5, 3, 6, 64, 7, 65)
ASPRS_BY_LABEL.flags.writeable = False

LABEL_BY_ASPRS: NDArray[np.uint8] = np.zeros(256, dtype=np.uint8)
"""Label value read for each ASPRS classification code of a file without a ``label`` dimension.

2 ground → 2 natural terrain, 3 low and 4 medium vegetation → 4 low vegetation, 5 high
vegetation → 3, 6 building → 5, 7 low point and 18 high noise → 7 scanning artefacts,
11 road surface → 1 man-made terrain; every other code (unclassified, water, wires,
bridges, user-definable 64..255 whose meaning varies between producers) → 0.
"""
for _code, _label in {2: 2, 3: 4, 4: 4, 5: 3, 6: 5, 7: 7, 11: 1, 18: 7}.items():
    LABEL_BY_ASPRS[_code] = _label
LABEL_BY_ASPRS.flags.writeable = False

_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


class CrsError(Semantic3DError, ValueError):
    """A coordinate reference system that pyproj cannot read."""


def parse_crs(crs: object) -> object:
    """``crs`` (``"EPSG:2154"``, a WKT string, a ``pyproj.CRS``...) as a ``pyproj.CRS``.

    Raises:
        CrsError: pyproj does not know it.
        MissingExtraError: pyproj is not installed (extra ``las``).
    """
    pyproj: Any = require("pyproj", "las")
    try:
        return pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError as exc:
        raise CrsError(
            f"expected a coordinate reference system such as EPSG:2154, found {crs!r} ({exc})"
        ) from None


_READ_ERRORS: tuple[type[BaseException], ...] = (laspy.errors.LaspyException, ValueError)


def _lazrs_error_types() -> tuple[type[BaseException], ...]:
    try:
        import lazrs
    except ImportError:
        return ()
    return (lazrs.LazrsError,)


def iter_las(
    path: str | Path,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    map_classification: bool = True,
) -> Iterator[PointCloud]:
    """Stream the points of a LAS/LAZ file in chunks of exactly ``chunk_size`` (the last may be shorter).

    Args:
        path: a ``.las`` or ``.laz`` file.
        chunk_size: points per chunk.
        map_classification: for files without a ``label`` dimension written by other
            software, derive labels from the ASPRS classification (:data:`LABEL_BY_ASPRS`);
            with False such files read without labels.

    Raises:
        DataFormatError: the file is not LAS/LAZ, is truncated or its fields are invalid.
        MissingExtraError: a LAZ file without the ``lazrs`` package.
    """
    chunk_size = validate_chunk_size(chunk_size)
    path = Path(path)
    if path.suffix.lower() == ".laz":
        _require_lazrs()
    return _iter_las(path, chunk_size, map_classification)


def read_las_header(path: str | Path) -> laspy.LasHeader:
    """The header of a LAS/LAZ file (point count, bounds, point format), read in O(1)."""
    with _open_reader(Path(path)) as reader:
        return reader.header


def _laz_backends() -> tuple[laspy.LazBackend, ...]:
    """Available LAZ backends, lazrs' multi-threaded one first (chunks on all cores)."""
    available = tuple(laspy.LazBackend.detect_available())
    parallel = laspy.LazBackend.LazrsParallel
    return tuple(b for b in available if b is parallel) + tuple(
        b for b in available if b is not parallel
    )


def _open_reader(path: Path) -> laspy.LasReader:
    try:
        return laspy.open(path, laz_backend=_laz_backends())
    except _READ_ERRORS + _lazrs_error_types() as exc:
        raise DataFormatError(
            f"expected a LAS/LAZ file, found one laspy cannot read: {exc}", path=str(path)
        ) from exc


def _iter_las(path: Path, chunk_size: int, map_classification: bool) -> Iterator[PointCloud]:
    errors = _READ_ERRORS + _lazrs_error_types()
    with _open_reader(path) as reader:
        header = reader.header
        expected = int(header.point_count)
        _check_uncompressed_size(path, header, expected)
        decoder = _ChunkDecoder(header, map_classification, path)
        records = reader.chunk_iterator(chunk_size)
        n_read = 0
        while True:
            try:
                record = next(records, None)
            except errors as exc:
                raise DataFormatError(
                    f"expected {expected} points, reading failed after {n_read}: {exc}",
                    path=str(path),
                ) from exc
            if record is None or len(record) == 0:
                break
            cloud = decoder.decode(record)
            n_read += cloud.n_points
            yield cloud
    if n_read != expected:
        raise DataFormatError(
            f"expected {expected} points (from the header), found {n_read}: truncated file?",
            path=str(path),
        )


def read_las(path: str | Path, *, map_classification: bool = True) -> PointCloud:
    """The whole LAS/LAZ file as one :class:`PointCloud` (a thin wrapper over :func:`iter_las`)."""
    chunks = list(iter_las(path, map_classification=map_classification))
    if not chunks:
        extra = set(read_las_header(path).point_format.extra_dimension_names)
        foreign = INTENSITY_DIMENSION not in extra
        return PointCloud.empty(
            with_labels=LABEL_DIMENSION in extra or (foreign and map_classification)
        )
    return chunks[0] if len(chunks) == 1 else PointCloud.concatenate(chunks)


class LasPointWriter(StagedWriter):
    """Writes point chunks to a LAS/LAZ file as they come (LAZ when the suffix is ``.laz``).

    The header (offsets, and whether a ``label`` dimension exists) is fixed by the first
    chunks: labels are stored when the first chunk has them (every later chunk must then
    have them too), offsets come from the first non-empty chunk. The file is written
    under a temporary name (:class:`~semantic3d.io.staging.StagedPath`) and renamed into
    place on close; on an exception inside the ``with`` block (Ctrl-C included) it is
    removed and the final name is left as it was.
    """

    def __init__(self, path: str | Path, *, crs: object = None) -> None:
        self.path = Path(path)
        self.n_points = 0
        self.compress = self.path.suffix.lower() == ".laz"
        if self.compress:
            _require_lazrs()
        self.crs = None if crs is None else parse_crs(crs)
        self._has_labels: bool | None = None
        self._writer: laspy.LasWriter | None = None
        self._offsets = np.zeros(3)
        self._staged = StagedPath(self.path)
        # Claim the file now so that an unwritable destination fails before any work.
        self._staged.temp.open("wb").close()

    def write(self, cloud: PointCloud) -> None:
        """Append ``cloud``."""
        if self._has_labels is None:
            self._has_labels = cloud.labels is not None
        self.check_labels(cloud, self._has_labels)
        if cloud.n_points == 0:
            return
        finite = np.isfinite(cloud.xyz).all(axis=1)
        if not finite.all():
            row = int(np.flatnonzero(~finite)[0])
            raise DataFormatError(
                f"point #{self.n_points + row}: expected finite coordinates, found "
                f"{cloud.xyz[row].tolist()}",
                path=str(self.path),
            )
        writer = self._writer or self._open(np.floor(cloud.xyz.min(axis=0)))
        writer.write_points(self._encode(cloud, writer.header))
        self.n_points += cloud.n_points

    def _open(self, offsets: NDArray[np.float64]) -> laspy.LasWriter:
        header = laspy.LasHeader(point_format=POINT_FORMAT, version=LAS_VERSION)
        header.scales = np.full(3, COORDINATE_SCALE_M)
        header.offsets = offsets
        header.generating_software = f"semantic3d {__version__}"[:32]
        header.system_identifier = "semantic3d"
        # LAS 1.4 R15, 2.4: point formats 6-10 describe their CRS in WKT, and the bit must be
        # set even when no CRS record is present.
        header.global_encoding.wkt = True
        if self.crs is not None:
            header.add_crs(self.crs)
        extra = [
            laspy.ExtraBytesParams(
                INTENSITY_DIMENSION, np.int32, description="exact; intensity = this + 2048"
            )
        ]
        if self._has_labels:
            extra.append(
                laspy.ExtraBytesParams(LABEL_DIMENSION, np.uint8, description="semantic3d label")
            )
        header.add_extra_dims(extra)
        self._offsets = np.asarray(offsets, dtype=np.float64)
        self._writer = laspy.open(
            self._staged.temp,
            mode="w",
            header=header,
            do_compress=self.compress,
            laz_backend=_laz_backends(),
        )
        return self._writer

    def _encode(self, cloud: PointCloud, header: laspy.LasHeader) -> laspy.ScaleAwarePointRecord:
        record = laspy.ScaleAwarePointRecord.zeros(cloud.n_points, header=header)
        ints = np.rint((cloud.xyz - self._offsets) / COORDINATE_SCALE_M)
        bad = ~((ints >= _INT32_MIN) & (ints <= _INT32_MAX)).all(axis=1)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise DataFormatError(
                f"point #{self.n_points + row} at {cloud.xyz[row].tolist()}: expected "
                f"coordinates within ±2^31 mm (±2147 km) of the offset "
                f"{self._offsets.tolist()} fixed from the first chunk (LAS stores int32 "
                f"millimetres), found one further away",
                path=str(self.path),
            )
        record.X, record.Y, record.Z = (ints[:, axis].astype(np.int32) for axis in range(3))
        record.intensity = np.clip(
            cloud.intensity.astype(np.int64) + INTENSITY_OFFSET, 0, 65535
        ).astype(np.uint16)
        record[INTENSITY_DIMENSION] = cloud.intensity
        rgb16 = cloud.rgb.astype(np.uint16) * np.uint16(257)
        record.red, record.green, record.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
        record.return_number = np.ones(cloud.n_points, np.uint8)
        record.number_of_returns = np.ones(cloud.n_points, np.uint8)
        if cloud.labels is not None:
            record.classification = ASPRS_BY_LABEL[cloud.labels]
            record[LABEL_DIMENSION] = cloud.labels
        return record

    def close(self) -> None:
        """Write the header's final counts and bounds and close the file."""
        writer = self._writer or self._open(np.zeros(3))
        writer.close()
        self._staged.commit()

    def abort(self) -> None:
        """Close and remove the partial file; the final path is left as it was."""
        if self._writer is not None:
            # The original error matters, not one from closing a half-written file.
            with suppress(Exception):
                self._writer.close()
        self._staged.discard()


def open_las_writer(path: str | Path, *, crs: object = None) -> LasPointWriter:
    """Open a :class:`LasPointWriter` (LAZ when ``path`` ends in ``.laz``); use it with ``with``.

    ``crs`` (e.g. ``"EPSG:2154"``) is written as a WKT coordinate-system record.
    """
    return LasPointWriter(path, crs=crs)


def write_las(path: str | Path, chunks: Iterable[PointCloud], *, crs: object = None) -> int:
    """Write point chunks to a LAS/LAZ file without holding them all; return the count.

    ``crs`` (e.g. ``"EPSG:2154"``) is written as a WKT coordinate-system record.
    """
    return write_chunks(open_las_writer(path, crs=crs), chunks)


class _ChunkDecoder:
    """Turns laspy point records into clouds; remembers per-file decisions across chunks."""

    def __init__(self, header: laspy.LasHeader, map_classification: bool, path: Path) -> None:
        self.path = path
        names = set(header.point_format.dimension_names)
        extra = set(header.point_format.extra_dimension_names)
        self.exact_intensity = INTENSITY_DIMENSION in extra
        self.label_dimension = LABEL_DIMENSION in extra
        self.map_classification = map_classification and not self.exact_intensity
        self.has_rgb = {"red", "green", "blue"} <= names
        self.decimal = _decimal_grid(header)
        # Written here: always value * 257. Foreign: decided on the first coloured chunk.
        self.colour_shift: int | None = 8 if self.exact_intensity else None

    def decode(self, record: laspy.ScaleAwarePointRecord) -> PointCloud:
        n = len(record)
        xyz = np.empty((n, 3), dtype=np.float64)
        if self.decimal is None:
            xyz[:, 0], xyz[:, 1], xyz[:, 2] = record.x, record.y, record.z
        else:
            # X * 0.001 + offset is off by an ulp from the decimal value; (X + offset in
            # units) / 1000 is the correctly rounded double, the same bits as parsing
            # the decimal text, so LAS <-> ASCII round trips are exact.
            units, divisor = self.decimal
            for axis, name in enumerate("XYZ"):
                xyz[:, axis] = (np.asarray(record[name]).astype(np.int64) + units[axis]) / divisor
        if self.exact_intensity:
            intensity = np.asarray(record[INTENSITY_DIMENSION]).astype(np.int32)
        else:
            intensity = np.asarray(record.intensity).astype(np.int32)
        rgb = np.zeros((n, 3), dtype=np.uint8)
        if self.has_rgb:
            rgb16 = np.stack([record.red, record.green, record.blue], axis=1)
            if self.colour_shift is None and rgb16.any():
                self.colour_shift = 0 if rgb16.max() <= 255 else 8
            rgb = (rgb16 >> (self.colour_shift or 0)).astype(np.uint8)
        labels: NDArray[np.uint8] | None = None
        if self.label_dimension:
            labels = _as_labels(np.asarray(record[LABEL_DIMENSION]), self.path)
        elif self.map_classification:
            labels = LABEL_BY_ASPRS[np.asarray(record.classification).astype(np.uint8)]
        return PointCloud(xyz, intensity, rgb, labels)


def _decimal_grid(header: laspy.LasHeader) -> tuple[NDArray[np.int64], float] | None:
    """Offsets in whole units and ``10**k`` when every scale is ``10**-k`` (else None)."""
    scales = np.asarray(header.scales, dtype=np.float64)
    offsets = np.asarray(header.offsets, dtype=np.float64)
    for digits in range(10):
        if np.all(scales == 10.0**-digits):
            units = offsets * 10**digits
            if np.all(np.abs(units - np.rint(units)) < 1e-6) and np.all(np.abs(units) < 2**52):
                return np.rint(units).astype(np.int64), float(10**digits)
            return None
    return None


def _as_labels(values: np.ndarray, path: Path) -> NDArray[np.uint8]:
    if values.dtype == np.uint8:
        return values.copy()
    if values.size and (values.min() < 0 or values.max() > 255 or np.any(values % 1)):
        raise DataFormatError(
            f"expected integer labels 0..255 in the {LABEL_DIMENSION!r} dimension, found "
            f"values in {values.min()}..{values.max()}",
            path=str(path),
        )
    return values.astype(np.uint8)


def _check_uncompressed_size(path: Path, header: laspy.LasHeader, n_points: int) -> None:
    if header.are_points_compressed:
        return
    needed = header.offset_to_point_data + n_points * header.point_format.size
    found = path.stat().st_size
    if found < needed:
        raise DataFormatError(
            f"expected at least {needed} bytes for {n_points} points, found {found}: "
            "truncated file",
            path=str(path),
        )


def _require_lazrs() -> None:
    try:
        import lazrs  # noqa: F401
    except ImportError as exc:
        raise MissingExtraError("lazrs", "las") from exc
