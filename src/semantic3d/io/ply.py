"""PLY point files: binary little-endian, streamed in both directions.

Written vertex properties, in this order::

    double x, double y, double z       coordinates in metres (float64, nothing lost)
    int intensity                      the exact signed intensity (int32)
    uchar red, uchar green, uchar blue colour
    uchar scalar_label                 label value, only when the chunks carry labels

``scalar_label`` is the name CloudCompare gives a scalar field called ``label`` when it
saves a PLY; its loader turns every vertex property whose name contains ``scal`` into a
scalar field (dropping the ``scalar_`` prefix), and loads ``intensity`` as a scalar
field too, so the file opens without the property-assignment dialog.

Streaming write: the vertex count is not known until the last chunk, so the header is
written with the count left-justified in a fixed field of :data:`COUNT_WIDTH` characters
(padded with spaces before the newline) and patched in place on close. Every PLY parser
reads the count as the third whitespace-separated token of the line, so the padding is
invisible to them.

Reading memory-maps the vertex data of binary files through plyfile
(``PlyData.read(path, mmap="r")``) and copies out one chunk at a time. Also read:
big-endian files, files written by other software (float or double coordinates,
``scalar_intensity``, ``label``, 16-bit colours, float scalar fields holding integers).
ASCII PLY is read too, but plyfile parses it whole: memory grows with the file.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from semantic3d import __version__
from semantic3d.core.errors import DataFormatError, MissingExtraError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, validate_chunk_size
from semantic3d.io.staging import StagedPath, StagedWriter, write_chunks

try:
    import plyfile
except ImportError as _exc:  # pragma: no cover - exercised only without the extra
    raise MissingExtraError("plyfile", "ply") from _exc

__all__ = [
    "COUNT_WIDTH",
    "LABEL_PROPERTY",
    "PlyHeader",
    "PlyPointWriter",
    "iter_ply",
    "open_ply_writer",
    "read_ply",
    "read_ply_header",
    "write_ply",
]

LABEL_PROPERTY = "scalar_label"
"""Vertex property holding label values (CloudCompare shows it as the scalar field ``label``)."""

COUNT_WIDTH = 20
"""Characters reserved for the vertex count in the header (any uint64 fits)."""

_MAX_HEADER_BYTES = 1 << 20
_TYPE_BYTES = {
    **dict.fromkeys(("char", "uchar", "int8", "uint8"), 1),
    **dict.fromkeys(("short", "ushort", "int16", "uint16"), 2),
    **dict.fromkeys(("int", "uint", "float", "int32", "uint32", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}
_LABEL_NAMES = (LABEL_PROPERTY, "label")
_INTENSITY_NAMES = ("intensity", "scalar_intensity")
_PROPERTIES = (
    ("x", "double", "<f8"),
    ("y", "double", "<f8"),
    ("z", "double", "<f8"),
    ("intensity", "int", "<i4"),
    ("red", "uchar", "u1"),
    ("green", "uchar", "u1"),
    ("blue", "uchar", "u1"),
)
_LABEL = (LABEL_PROPERTY, "uchar", "u1")


def iter_ply(path: str | Path, *, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Iterator[PointCloud]:
    """Stream the vertices of a PLY file in chunks of exactly ``chunk_size`` (the last may be shorter).

    Needs ``x``, ``y`` and ``z`` vertex properties; intensity, colour and labels are read
    when present (zeros, zeros and no labels otherwise).

    Raises:
        DataFormatError: not a PLY file, truncated, no vertex element or no coordinates.
    """
    chunk_size = validate_chunk_size(chunk_size)
    path = Path(path)
    vertices = _open_vertices(path)
    return _iter_vertices(path, vertices, chunk_size)


def _iter_vertices(path: Path, vertices: np.ndarray, chunk_size: int) -> Iterator[PointCloud]:
    columns = _Columns(path, vertices.dtype)
    n_vertices = vertices.shape[0]
    if not isinstance(vertices, np.memmap):  # ASCII or list properties: already in memory
        for start in range(0, n_vertices, chunk_size):
            yield columns.decode(vertices[start : start + chunk_size])
        return
    # Binary: plyfile found the records' dtype and offset; read them sequentially rather
    # than through the map, whose touched pages would count as resident memory.
    offset, dtype = vertices.offset, vertices.dtype
    del vertices
    with path.open("rb") as stream:
        stream.seek(offset)
        for start in range(0, n_vertices, chunk_size):
            records = np.empty(min(chunk_size, n_vertices - start), dtype=dtype)
            if stream.readinto(records.data) != records.nbytes:
                raise DataFormatError(
                    f"expected {n_vertices} vertices, found the file ending before vertex "
                    f"#{start + records.shape[0] - 1}: truncated file",
                    path=str(path),
                )
            yield columns.decode(records)


def read_ply(path: str | Path) -> PointCloud:
    """The whole PLY file as one :class:`PointCloud` (a thin wrapper over :func:`iter_ply`)."""
    chunks = list(iter_ply(path))
    if not chunks:
        vertices = _open_vertices(Path(path))
        has_labels = any(name in (vertices.dtype.names or ()) for name in _LABEL_NAMES)
        return PointCloud.empty(with_labels=has_labels)
    return chunks[0] if len(chunks) == 1 else PointCloud.concatenate(chunks)


class PlyPointWriter(StagedWriter):
    """Writes point chunks to a binary little-endian PLY file as they come.

    The first chunk decides whether a ``scalar_label`` property exists; every later chunk
    must match. The vertex count is patched into the header on close, and the file, written
    under a temporary name (:class:`~semantic3d.io.staging.StagedPath`), renamed into
    place. On an exception inside the ``with`` block (Ctrl-C included) it is removed and
    the final name is left as it was.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.n_points = 0
        self._has_labels: bool | None = None
        self._count_at = 0
        self._dtype = np.dtype([])
        self._staged = StagedPath(self.path)
        self._stream: BinaryIO = self._staged.temp.open("wb")

    def write(self, cloud: PointCloud) -> None:
        """Append ``cloud``."""
        if self._has_labels is None:
            self._write_header(cloud.labels is not None)
        self.check_labels(cloud, bool(self._has_labels))
        if cloud.n_points == 0:
            return
        records = np.empty(cloud.n_points, dtype=self._dtype)
        records["x"], records["y"], records["z"] = cloud.xyz.T
        records["intensity"] = cloud.intensity
        records["red"], records["green"], records["blue"] = cloud.rgb.T
        if cloud.labels is not None:
            records[LABEL_PROPERTY] = cloud.labels
        self._stream.write(records.data)
        self.n_points += cloud.n_points

    def _write_header(self, has_labels: bool) -> None:
        self._has_labels = has_labels
        properties = _PROPERTIES + ((_LABEL,) if has_labels else ())
        self._dtype = np.dtype([(name, dtype) for name, _, dtype in properties])
        head = (
            "ply\nformat binary_little_endian 1.0\n"
            f"comment written by semantic3d {__version__}\n"
            "element vertex "
        ).encode("ascii")
        tail = "".join(f"property {kind} {name}\n" for name, kind, _ in properties)
        self._stream.write(head)
        self._count_at = len(head)
        self._stream.write(b" " * COUNT_WIDTH + b"\n" + f"{tail}end_header\n".encode("ascii"))

    def close(self) -> None:
        """Patch the vertex count into the header and close the file."""
        if self._stream.closed:
            return
        if self._has_labels is None:
            self._write_header(False)
        self._stream.seek(self._count_at)
        self._stream.write(str(self.n_points).ljust(COUNT_WIDTH).encode("ascii"))
        self._stream.close()
        self._staged.commit()

    def abort(self) -> None:
        """Close and remove the partial file; the final path is left as it was."""
        self._stream.close()
        self._staged.discard()


def open_ply_writer(path: str | Path) -> PlyPointWriter:
    """Open a :class:`PlyPointWriter`; use it as a context manager."""
    return PlyPointWriter(path)


def write_ply(path: str | Path, chunks: Iterable[PointCloud]) -> int:
    """Write point chunks to a binary PLY file without holding them all; return the count."""
    return write_chunks(open_ply_writer(path), chunks)


@dataclass(frozen=True, slots=True)
class PlyHeader:
    """What a PLY header says about the vertices, read without touching the body."""

    storage: str
    """``binary_little_endian``, ``binary_big_endian`` or ``ascii``."""
    n_vertices: int
    vertex_properties: tuple[str, ...]
    """``"name type"`` for each vertex property, in file order."""


def read_ply_header(path: str | Path) -> PlyHeader:
    """Parse the header of a PLY file (O(1): the body is not read).

    The vertex count is checked against the file's size: every vertex takes at least its
    properties' bytes (binary) or two characters per property (ASCII), so a header that
    claims more vertices than the file can hold is refused here, before anything is
    allocated for them.
    """
    path = Path(path)
    header, least, body_bytes = _parse_header(path)
    _check_vertex_count(path, header, least, body_bytes)
    return header


def _check_vertex_count(path: Path, header: PlyHeader, least: int, body_bytes: int) -> None:
    if least > body_bytes:
        raise DataFormatError(
            f"the header declares {header.n_vertices:,} vertices, which take at least "
            f"{least:,} bytes, found {body_bytes:,} bytes after the header: truncated file "
            "or corrupt header",
            path=str(path),
        )


def _parse_header(path: Path) -> tuple[PlyHeader, int, int]:
    """The header, the least bytes its vertices take and the bytes after the header."""
    storage, n_vertices, properties = "", -1, []
    element = ""
    vertex_bytes = 0  # the least bytes one vertex takes in a binary body
    with path.open("rb") as stream:
        if stream.readline().rstrip(b"\r\n") != b"ply":
            raise DataFormatError("expected a PLY file (first line 'ply')", path=str(path))
        for raw in stream:
            tokens = raw.decode("ascii", errors="replace").split()
            if tokens[:1] == ["end_header"]:
                break
            if tokens[:1] == ["format"] and len(tokens) >= 2:
                storage = tokens[1]
            elif tokens[:1] == ["element"] and len(tokens) == 3:
                element = tokens[1]
                if element == "vertex" and tokens[2].isdigit():
                    n_vertices = int(tokens[2])
            elif tokens[:1] == ["property"] and element == "vertex":
                properties.append(f"{tokens[-1]} {' '.join(tokens[1:-1])}")
                # a list property takes at least its count (an empty list)
                kind = tokens[2] if tokens[1:2] == ["list"] and len(tokens) > 2 else tokens[1]
                vertex_bytes += _TYPE_BYTES.get(kind, 1) if len(tokens) > 2 else 1
            if stream.tell() > _MAX_HEADER_BYTES:
                break
        else:
            raise DataFormatError("expected 'end_header', found end of file", path=str(path))
        body_bytes = path.stat().st_size - stream.tell()
    if n_vertices < 0 or not storage:
        raise DataFormatError(
            "expected a 'format' line and an 'element vertex N' line in the header",
            path=str(path),
        )
    least = n_vertices * (2 * len(properties) if storage == "ascii" else vertex_bytes)
    return PlyHeader(storage, n_vertices, tuple(properties)), least, body_bytes


def _open_vertices(path: Path) -> np.ndarray:
    """The vertex records of ``path``: a read-only memory map for binary files."""
    try:
        parsed = _parse_header(path)
    except DataFormatError:
        pass  # not a PLY header: plyfile's own message says why, below
    else:
        _check_vertex_count(path, *parsed)  # before plyfile allocates the vertices
    try:
        data = plyfile.PlyData.read(str(path), mmap="r")
    except (plyfile.PlyParseError, ValueError, UnicodeDecodeError) as exc:
        raise DataFormatError(
            f"expected a readable PLY file, found: {exc}", path=str(path)
        ) from exc
    if "vertex" not in data:
        found = ", ".join(element.name for element in data.elements) or "no elements"
        raise DataFormatError(f"expected a 'vertex' element, found {found}", path=str(path))
    vertices = data["vertex"].data
    missing = [axis for axis in "xyz" if axis not in (vertices.dtype.names or ())]
    if missing:
        found = " ".join(vertices.dtype.names or ())
        raise DataFormatError(
            f"expected vertex properties x y z, missing {' '.join(missing)} (found {found})",
            path=str(path),
        )
    return vertices


class _Columns:
    """Which vertex properties hold which point column, and how to convert them."""

    def __init__(self, path: Path, dtype: np.dtype) -> None:
        names = dtype.names or ()
        self.path = path
        self.intensity = next((n for n in _INTENSITY_NAMES if n in names), None)
        self.label = next((n for n in _LABEL_NAMES if n in names), None)
        self.rgb = ("red", "green", "blue") if {"red", "green", "blue"} <= set(names) else None
        self.colour_shift = 0
        if self.rgb is not None and any(dtype[name].itemsize > 1 for name in self.rgb):
            self.colour_shift = 8

    def decode(self, records: np.ndarray) -> PointCloud:
        n = records.shape[0]
        xyz = np.empty((n, 3), dtype=np.float64)
        xyz[:, 0], xyz[:, 1], xyz[:, 2] = records["x"], records["y"], records["z"]
        intensity = (
            np.zeros(n, np.int32)
            if self.intensity is None
            else self._integers(records[self.intensity], self.intensity, np.int32)
        )
        rgb = np.zeros((n, 3), dtype=np.uint8)
        if self.rgb is not None:
            for axis, name in enumerate(self.rgb):
                rgb[:, axis] = np.asarray(records[name]).astype(np.int64) >> self.colour_shift
        labels = None
        if self.label is not None:
            labels = self._integers(records[self.label], self.label, np.uint8)
        return PointCloud(xyz, intensity, rgb, labels)

    def _integers(
        self, values: np.ndarray, name: str, dtype: type[np.int32] | type[np.uint8]
    ) -> np.ndarray:
        values = np.asarray(values)
        if values.dtype == dtype:
            return values.astype(dtype)  # a copy in native byte order, off the memory map
        info = np.iinfo(dtype)
        if values.size and (
            not np.isfinite(values).all()
            or values.min() < info.min
            or values.max() > info.max
            or np.any(values != np.rint(values))
        ):
            raise DataFormatError(
                f"expected integers in {info.min}..{info.max} in vertex property {name!r}, "
                f"found values in {values.min()}..{values.max()}",
                path=str(self.path),
            )
        return np.rint(values).astype(dtype)
