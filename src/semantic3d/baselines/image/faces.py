"""Cube faces as the classifiers see them, and labels between faces and points.

A :class:`Face` is one cube face: colours, which pixels show a point, the elevation angle
of every pixel (where on the sphere it looks) and, for training, label values with the
scanning artefacts (class 7) removed: the paper ignores them in 2D ("not present in the
image data").
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.pointcloud import PointCloud
from semantic3d.viz.cubemap import NO_POINT, CubeMap, face_bases, project_points

__all__ = [
    "IGNORED_LABEL",
    "Face",
    "cube_faces",
    "face_elevation",
    "labels_through_index",
    "tee_pixels",
]

IGNORED_LABEL = 7
"""Scanning artefacts: not trained on and never predicted in 2D."""


@dataclass(frozen=True, slots=True)
class Face:
    """One cube face.

    Attributes:
        rgb: ``(s, s, 3)`` uint8 colours (black where no point).
        valid: ``(s, s)`` whether a pixel shows a point.
        elevation: ``(s, s)`` float32 elevation angle of the pixel's ray, radians.
        labels: ``(s, s)`` uint8 training label values (0: unlabelled, no point or class 7),
            or None.
    """

    rgb: NDArray[np.uint8]
    valid: NDArray[np.bool_]
    elevation: NDArray[np.float32]
    labels: NDArray[np.uint8] | None = None


def face_elevation(size: int) -> NDArray[np.float32]:
    """``(6, size, size)`` elevation angle (radians) of each pixel centre's ray."""
    bases = face_bases()
    centres = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    u = centres[None, :]
    v = -centres[:, None]
    out = np.empty((6, size, size), np.float32)
    for face in range(6):
        forward, right, up = bases[face]
        direction = forward[:, None, None] + right[:, None, None] * u + up[:, None, None] * v
        out[face] = np.arctan2(direction[2], np.hypot(direction[0], direction[1]))
    return out


def cube_faces(cubemap: CubeMap) -> list[Face]:
    """The six faces of a cube map; label faces (class 7 removed) when it has labels."""
    elevation = face_elevation(cubemap.size)
    valid = cubemap.has_point
    faces = []
    for number in range(6):
        labels = None
        if cubemap.labels is not None:
            labels = np.where(
                valid[number] & (cubemap.labels[number] != IGNORED_LABEL),
                cubemap.labels[number],
                0,
            ).astype(np.uint8)
        faces.append(Face(cubemap.rgb[number], valid[number], elevation[number], labels))
    return faces


def tee_pixels(
    chunks: Iterable[PointCloud], *, station: tuple[float, float, float], size: int, path: Path
) -> Iterator[PointCloud]:
    """Pass ``chunks`` through, writing each point's flat pixel number (int32) to ``path``.

    The file is what takes labels back to the points after the faces are classified,
    one chunk at a time, without keeping the scan in memory.
    """
    with path.open("wb") as stream:
        for chunk in chunks:
            project_points(chunk.xyz, station=station, size=size).flat(size).astype(
                np.int32
            ).tofile(stream)
            yield chunk


def labels_through_index(
    point_index: NDArray[np.int64], label_chunks: Iterable[NDArray[np.uint8]]
) -> NDArray[np.uint8]:
    """Label faces of a scan's labels: each pixel takes the label of the point it shows.

    ``label_chunks`` stream the label values in scan order (a ``.labels`` file); pixels
    without a point get 0.
    """
    flat_index = point_index.reshape(-1)
    order = np.argsort(flat_index, kind="stable")
    sorted_index = flat_index[order]
    out = np.zeros(flat_index.size, np.uint8)
    start = 0
    for chunk in label_chunks:
        stop = start + chunk.size
        low = np.searchsorted(sorted_index, start, side="left")
        high = np.searchsorted(sorted_index, stop, side="left")
        pixels = order[low:high]
        out[pixels] = chunk[sorted_index[low:high] - start]
        start = stop
    out[flat_index == NO_POINT] = 0
    return out.reshape(point_index.shape)
