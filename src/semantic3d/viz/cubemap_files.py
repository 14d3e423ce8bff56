"""Cube maps on disk: PNG faces (Pillow), the index faces and a JSON description.

:func:`write_cubemap` writes into a folder

- ``rgb_<face>.png``: the colour faces;
- ``labels_<face>.png``: the label faces in the paper's colours (classes in the benchmark
  colours, white unlabelled, black no point), when the scan had labels;
- ``index.npy``: ``(6, size, size)`` int64, the scan position of the point each pixel shows
  (-1: none), which takes labels back to the points exactly;
- ``cubemap.json``: station, size, face order and geometry, splat radius, points.

Every file is written under a temporary name and renamed into place; existing files are
refused (all checked before anything is written) unless ``overwrite``.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import refuse_existing_paths, require
from semantic3d.viz.cubemap import FACE_NAMES, CubeMap

__all__ = [
    "cubemap_outputs",
    "side_by_side",
    "write_cubemap",
    "write_png",
]

_DESCRIPTION = "cubemap.json"
_INDEX = "index.npy"


def cubemap_outputs(out: str | Path, *, with_labels: bool = True) -> list[Path]:
    """Every file :func:`write_cubemap` writes into ``out``."""
    folder = Path(out)
    kinds = ("rgb", "labels") if with_labels else ("rgb",)
    faces = [folder / f"{kind}_{face}.png" for kind in kinds for face in FACE_NAMES]
    return [*faces, folder / _INDEX, folder / _DESCRIPTION]


def _atomic(path: Path, write: Callable[[Path], object]) -> None:
    temp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.partial{path.suffix}")
    try:
        write(temp)
        temp.replace(path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def write_png(path: str | Path, image: NDArray[np.uint8]) -> Path:
    """Write an ``(h, w, 3)`` or ``(h, w)`` uint8 image as PNG, atomically."""
    pil = require("PIL.Image", "image")
    path = Path(path)

    def write(temp: Path) -> None:
        pil.fromarray(np.ascontiguousarray(image)).save(temp, format="PNG")  # type: ignore[attr-defined]

    _atomic(path, write)
    return path


def side_by_side(*images: NDArray[np.uint8], gap_px: int = 4) -> NDArray[np.uint8]:
    """Equal-height ``(h, w, 3)`` images joined left to right with a white gap."""
    height = images[0].shape[0]
    gap = np.full((height, gap_px, 3), 255, np.uint8)
    parts: list[NDArray[np.uint8]] = []
    for image in images:
        if parts:
            parts.append(gap)
        parts.append(image)
    return np.concatenate(parts, axis=1)


def write_cubemap(cubemap: CubeMap, out: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Write ``cubemap``'s faces, index and description into the folder ``out``.

    Raises:
        OutputExistsError: a file exists and ``overwrite`` is False (nothing is written).
    """
    folder = Path(out)
    with_labels = cubemap.labels is not None
    paths = cubemap_outputs(folder, with_labels=with_labels)
    refuse_existing_paths(paths, overwrite=overwrite)
    folder.mkdir(parents=True, exist_ok=True)
    for number, face in enumerate(FACE_NAMES):
        write_png(folder / f"rgb_{face}.png", cubemap.rgb[number])
    if with_labels:
        label_faces = cubemap.label_image()
        for number, face in enumerate(FACE_NAMES):
            write_png(folder / f"labels_{face}.png", label_faces[number])
    _atomic(folder / _INDEX, lambda temp: np.save(temp, cubemap.point_index))
    description = {
        "format": "semantic3d-cubemap",
        "format_version": 1,
        "station_m": list(cubemap.station),
        "size_px": cubemap.size,
        "faces": list(FACE_NAMES),
        "geometry": "faces along world axes; see semantic3d.viz.cubemap",
        "splat_radius_px": cubemap.splat_radius_px,
        "n_points": cubemap.n_points,
        "coverage": cubemap.coverage(),
        "index": _INDEX,
    }
    _atomic(
        folder / _DESCRIPTION,
        lambda temp: temp.write_text(json.dumps(description, indent=2) + "\n", encoding="utf-8"),
    )
    return paths
