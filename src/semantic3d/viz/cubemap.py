"""Cube maps of a scan: its points splatted onto the six faces of a cube around the station.

The paper's 2D baseline turns point labelling into image segmentation by converting each
scan's colours to images "with cube mapping" and projecting its ground truth the same way.
Here each scan is rendered from its scanner's station onto the six faces of a cube:
colour faces, label faces (the same projection of the ground truth) and an *index face*
saying which point each pixel shows, so labels go back to the points exactly.

Geometry. Faces follow the world axes, in the order :data:`FACE_NAMES` (``px`` looks
along +x, ``pz`` up). A point ``p`` seen from station ``s`` has direction ``d = p - s``; it
falls on the face whose forward axis has the largest component of ``d`` (ties go to the
earlier face), at ``u = d·right / d·forward`` and ``v = d·up / d·forward`` in [-1, 1],
pixel column ``floor((u + 1) / 2 · size)`` and row ``floor((1 - v) / 2 · size)`` (clipped to
the face). The four side faces have z up; the top face's bottom edge meets the ``px``
face's top edge, the bottom face's top edge its bottom edge, so the faces unfold into the
usual cross. A point straight ahead of a face lands at pixel ``(size // 2, size // 2)``.

Z-buffer. Each pixel shows the nearest point (smallest range ``|d|``); on equal ranges
the point read first wins, so a render does not depend on how the scan is chunked. With
``splat_radius_px = r`` a point also covers the ``(2r + 1)²`` square around its pixel
(within its face) under the same depth test, which closes the holes between the points of
distant surfaces. Memory is set by the faces (17 bytes a pixel), never by the scan:
chunks are splatted as they are read.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.classes import label_palette
from semantic3d.core.errors import Semantic3DError, ShapeError
from semantic3d.core.pointcloud import PointCloud

__all__ = [
    "FACE_NAMES",
    "NO_POINT",
    "CubeMap",
    "CubeMapError",
    "CubePixels",
    "face_bases",
    "project_points",
    "render_cubemap",
    "validate_size",
]

FACE_NAMES = ("px", "py", "nx", "ny", "pz", "nz")
"""The faces, in order: looking along +x, +y, -x, -y, up (+z), down (-z)."""

NO_POINT = -1
"""``point_index`` of a pixel that shows no point."""

MAX_SIZE = 16384
"""Largest face edge in pixels (6 faces of it index fit in int32 flat pixel numbers)."""

# Rows: forward, right, up of each face (see the module docstring).
_BASES = np.array(
    [
        [[1, 0, 0], [0, -1, 0], [0, 0, 1]],
        [[0, 1, 0], [1, 0, 0], [0, 0, 1]],
        [[-1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[0, -1, 0], [-1, 0, 0], [0, 0, 1]],
        [[0, 0, 1], [0, -1, 0], [-1, 0, 0]],
        [[0, 0, -1], [0, -1, 0], [1, 0, 0]],
    ],
    dtype=np.float64,
)

# Which face is the major axis's: index by axis * 2 + (component < 0).
_FACE_OF_AXIS = np.array([0, 2, 1, 3, 4, 5], dtype=np.int64)


class CubeMapError(Semantic3DError, ValueError):
    """A cube-map parameter or station is not usable."""


def validate_size(size: int) -> int:
    """``size`` as an int, or :class:`CubeMapError` unless 1..MAX_SIZE."""
    if isinstance(size, bool) or int(size) != size or not 1 <= size <= MAX_SIZE:
        raise CubeMapError(f"size: expected a face edge of 1..{MAX_SIZE} pixels, found {size!r}")
    return int(size)


def face_bases() -> NDArray[np.float64]:
    """``(6, 3, 3)``: per face, the forward, right and up unit vectors (rows)."""
    return _BASES.copy()


@dataclass(frozen=True, slots=True)
class CubePixels:
    """Where points fall on a cube map.

    Attributes:
        face: ``(n,)`` int8 face number (index into :data:`FACE_NAMES`); -1 for a point at
            the station itself (no direction).
        row, col: ``(n,)`` int32 pixel of the point on its face.
        range_m: ``(n,)`` float32 distance from the station.
    """

    face: NDArray[np.int8]
    row: NDArray[np.int32]
    col: NDArray[np.int32]
    range_m: NDArray[np.float32]

    def flat(self, size: int) -> NDArray[np.int64]:
        """Flat pixel numbers ``(face * size + row) * size + col`` (-1 without a face)."""
        flat = (self.face.astype(np.int64) * size + self.row) * size + self.col
        flat[self.face < 0] = -1
        return flat


# The two kernels below are hand-written because the z-buffer is a scatter-argmin with a
# payload: numpy has no such ufunc, and emulating it needs a sort of every chunk (and of
# the splat copies, (2r + 1)² per point) plus a merge with the faces so far; benchmarks/
# bench_cubemap.py measures that version against this one.


@numba.njit(cache=True, nogil=True)
def _pixel_of(
    x: float, y: float, z: float, bases: NDArray[np.float64], size: int
) -> tuple[int, int, int]:
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        axis, comp = 0, x
    elif ay >= az:
        axis, comp = 1, y
    else:
        axis, comp = 2, z
    if comp == 0.0:
        return -1, 0, 0
    face = _FACE_OF_AXIS[axis * 2 + (1 if comp < 0 else 0)]
    forward = x * bases[face, 0, 0] + y * bases[face, 0, 1] + z * bases[face, 0, 2]
    u = (x * bases[face, 1, 0] + y * bases[face, 1, 1] + z * bases[face, 1, 2]) / forward
    v = (x * bases[face, 2, 0] + y * bases[face, 2, 1] + z * bases[face, 2, 2]) / forward
    col = int(np.floor((u + 1.0) * 0.5 * size))
    row = int(np.floor((1.0 - v) * 0.5 * size))
    col = min(max(col, 0), size - 1)
    row = min(max(row, 0), size - 1)
    return face, row, col


@numba.njit(cache=True, nogil=True)
def _project_kernel(
    xyz: NDArray[np.float64],
    station: NDArray[np.float64],
    bases: NDArray[np.float64],
    size: int,
    face_out: NDArray[np.int8],
    row_out: NDArray[np.int32],
    col_out: NDArray[np.int32],
    range_out: NDArray[np.float32],
) -> None:
    for i in range(xyz.shape[0]):
        x = xyz[i, 0] - station[0]
        y = xyz[i, 1] - station[1]
        z = xyz[i, 2] - station[2]
        face, row, col = _pixel_of(x, y, z, bases, size)
        face_out[i] = face
        row_out[i] = row
        col_out[i] = col
        range_out[i] = np.sqrt(x * x + y * y + z * z)


@numba.njit(cache=True, nogil=True)
def _splat_kernel(
    xyz: NDArray[np.float64],
    rgb: NDArray[np.uint8],
    labels: NDArray[np.uint8],
    has_labels: bool,
    first_index: int,
    station: NDArray[np.float64],
    bases: NDArray[np.float64],
    radius: int,
    depth: NDArray[np.float32],
    index: NDArray[np.int64],
    rgb_faces: NDArray[np.uint8],
    label_faces: NDArray[np.uint8],
) -> None:
    size = depth.shape[1]
    for i in range(xyz.shape[0]):
        x = xyz[i, 0] - station[0]
        y = xyz[i, 1] - station[1]
        z = xyz[i, 2] - station[2]
        face, row, col = _pixel_of(x, y, z, bases, size)
        if face < 0:
            continue
        distance = np.float32(np.sqrt(x * x + y * y + z * z))
        for r in range(max(row - radius, 0), min(row + radius + 1, size)):
            for c in range(max(col - radius, 0), min(col + radius + 1, size)):
                if distance < depth[face, r, c]:
                    depth[face, r, c] = distance
                    index[face, r, c] = first_index + i
                    rgb_faces[face, r, c, 0] = rgb[i, 0]
                    rgb_faces[face, r, c, 1] = rgb[i, 1]
                    rgb_faces[face, r, c, 2] = rgb[i, 2]
                    if has_labels:
                        label_faces[face, r, c] = labels[i]


def project_points(
    xyz: NDArray[np.float64], *, station: tuple[float, float, float], size: int
) -> CubePixels:
    """The face, pixel and range of each point seen from ``station`` on faces of ``size``²."""
    size = validate_size(size)
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ShapeError(f"xyz: expected an (n, 3) array, found {xyz.shape}")
    n = xyz.shape[0]
    pixels = CubePixels(
        np.empty(n, np.int8), np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n, np.float32)
    )
    _project_kernel(
        xyz,
        np.asarray(station, np.float64),
        _BASES,
        size,
        pixels.face,
        pixels.row,
        pixels.col,
        pixels.range_m,
    )
    return pixels


@dataclass(frozen=True, slots=True)
class CubeMap:
    """Six rendered faces of a scan.

    Attributes:
        station: the viewpoint, scan coordinates in metres.
        size: face edge in pixels.
        depth_m: ``(6, size, size)`` float32 range of the shown point (inf: none).
        point_index: ``(6, size, size)`` int64 position in the scan of the shown point
            (:data:`NO_POINT`: none).
        rgb: ``(6, size, size, 3)`` uint8 colour of the shown point (black: none).
        labels: ``(6, size, size)`` uint8 label value of the shown point (0 where none),
            or None when the scan had no labels.
        n_points: points rendered (the scan's).
        splat_radius_px: the splat radius used.
    """

    station: tuple[float, float, float]
    size: int
    depth_m: NDArray[np.float32]
    point_index: NDArray[np.int64]
    rgb: NDArray[np.uint8]
    labels: NDArray[np.uint8] | None
    n_points: int
    splat_radius_px: int = 0

    @property
    def has_point(self) -> NDArray[np.bool_]:
        """``(6, size, size)``: whether a pixel shows a point."""
        return self.point_index != NO_POINT

    def coverage(self) -> float:
        """Share of the pixels of all faces that show a point."""
        return float(self.has_point.mean())

    def label_image(self, labels: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
        """``(6, size, size, 3)`` label faces in the colours of the paper's Figure 2.

        Classes in the benchmark colours, white where the shown point is unlabelled (0),
        black where no point is shown. ``labels`` (``(6, size, size)`` label values, e.g.
        a prediction) replaces the map's own.
        """
        values = self.labels if labels is None else labels
        if values is None:
            raise CubeMapError("label faces: the scan was rendered without labels")
        if values.shape != self.point_index.shape:
            raise ShapeError(f"labels: expected {self.point_index.shape}, found {np.shape(values)}")
        palette = label_palette()
        palette[0] = (255, 255, 255)
        image = palette[np.minimum(values, palette.shape[0] - 1)]
        image[~self.has_point] = 0
        return image


def render_cubemap(
    chunks: Iterable[PointCloud],
    *,
    station: tuple[float, float, float],
    size: int = 2048,
    splat_radius_px: int = 0,
    with_labels: bool = True,
    progress: Callable[[int], None] | None = None,
) -> CubeMap:
    """Render streamed points onto the six faces of a cube around ``station``.

    Args:
        chunks: the scan's points, in scan order (``io.iter_points``); point ``k`` of the
            stream is ``point_index`` ``k``.
        station: viewpoint in scan coordinates (metres).
        size: face edge in pixels.
        splat_radius_px: each point also covers the pixels within this many pixels of its
            own (square), under the depth test.
        with_labels: render label faces when the chunks carry labels.
        progress: called with the points rendered so far after each chunk.

    Raises:
        CubeMapError: a bad size, radius or station.
    """
    size = validate_size(size)
    if isinstance(splat_radius_px, bool) or int(splat_radius_px) != splat_radius_px:
        raise CubeMapError(f"splat_radius_px: expected an integer, found {splat_radius_px!r}")
    if not 0 <= splat_radius_px <= 16:
        raise CubeMapError(f"splat_radius_px: expected 0..16, found {splat_radius_px}")
    station_arr = np.asarray(station, np.float64)
    if station_arr.shape != (3,) or not np.isfinite(station_arr).all():
        raise CubeMapError(f"station: expected 3 finite coordinates, found {station!r}")
    depth = np.full((6, size, size), np.inf, np.float32)
    index = np.full((6, size, size), NO_POINT, np.int64)
    rgb = np.zeros((6, size, size, 3), np.uint8)
    labels = np.zeros((6, size, size), np.uint8)
    seen_labels: bool | None = None
    no_labels = np.zeros(0, np.uint8)
    done = 0
    for chunk in chunks:
        chunk_labels = chunk.labels if with_labels else None
        has = chunk_labels is not None
        seen_labels = has if seen_labels is None else (seen_labels and has)
        _splat_kernel(
            chunk.xyz,
            chunk.rgb,
            chunk_labels if chunk_labels is not None else no_labels,
            has,
            done,
            station_arr,
            _BASES,
            int(splat_radius_px),
            depth,
            index,
            rgb,
            labels,
        )
        done += chunk.n_points
        if progress is not None:
            progress(done)
    return CubeMap(
        station=(float(station_arr[0]), float(station_arr[1]), float(station_arr[2])),
        size=size,
        depth_m=depth,
        point_index=index,
        rgb=rgb,
        labels=labels if seen_labels else None,
        n_points=done,
        splat_radius_px=int(splat_radius_px),
    )
