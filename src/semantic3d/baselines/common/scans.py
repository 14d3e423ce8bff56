"""The labelled scans a baseline trains on: any supported format, found in a folder or the registry.

A training folder holds scans in any format ``io`` reads: ``NAME.txt`` with its
``NAME.labels`` beside it, or ``NAME.las`` / ``NAME.laz`` / ``NAME.ply`` / a ``NAME.cache``
folder carrying their labels inside. For the benchmark's own training split, scans are
found under their distributed file names through :class:`~semantic3d.datasets.Semantic3D`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import Semantic3DError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE

__all__ = ["LabelledScan", "TrainingDataError", "find_labelled_scans"]

_EMBEDDED_SUFFIXES = (".las", ".laz", ".ply", ".cache")


class TrainingDataError(Semantic3DError, ValueError):
    """The training scans cannot train a model (none found, no labels, a class missing, ...)."""


@dataclass(frozen=True, slots=True)
class LabelledScan:
    """A scan and where its labels are.

    Attributes:
        name: the scan's name (file stem, or registry name).
        points_path: the points file (any format) or cache folder.
        labels_path: the ``.labels`` file, or None when the points file carries the labels.
    """

    name: str
    points_path: Path
    labels_path: Path | None = None

    def iter_points(self, *, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Iterator[PointCloud]:
        """The scan's points with their labels, streamed."""
        from semantic3d.io.formats import iter_points

        return iter_points(self.points_path, labels_path=self.labels_path, chunk_size=chunk_size)

    def iter_labels(self, *, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Iterator[NDArray[np.uint8]]:
        """The scan's label values in point order, streamed (the ``.labels`` file alone if any)."""
        if self.labels_path is not None:
            from semantic3d.io.labels import iter_labels

            yield from iter_labels(self.labels_path, chunk_size=chunk_size)
            return
        for chunk in self.iter_points(chunk_size=chunk_size):
            if chunk.labels is None:
                raise TrainingDataError(
                    f"{self.points_path}: training needs labels: expected a label column, "
                    "found none"
                )
            yield chunk.labels


def find_labelled_scans(
    data_dir: str | Path, *, names: Sequence[str] = (), split: str | None = None
) -> tuple[LabelledScan, ...]:
    """The labelled scans of ``data_dir`` (all, or ``names``), sorted by name unless named.

    Args:
        data_dir: a folder of scans.
        names: the scans to take, by name (file stem); default every scan found.
        split: a registry split (``training``): take its scans under their distributed
            file names instead of looking at every file.

    Raises:
        TrainingDataError: no scan found, a named scan missing, a scan without labels, or
            two files with the same name.
    """
    folder = Path(data_dir)
    if not folder.is_dir():
        raise TrainingDataError(f"{folder}: expected a folder of NAME.txt + NAME.labels scans")
    available = _registry_scans(folder, split) if split else _folder_scans(folder)
    wanted = list(names) if names else sorted(available)
    missing = [n for n in wanted if n not in available]
    if missing:
        raise TrainingDataError(
            f"{folder}: scan(s) {missing} not found: expected NAME.txt files among "
            f"{sorted(available) or 'none'}"
        )
    if not wanted:
        raise TrainingDataError(f"{folder}: no NAME.txt scan found")
    return tuple(_with_labels(available[name], name) for name in wanted)


def _folder_scans(folder: Path) -> dict[str, Path]:
    from semantic3d.io.formats import ASCII_SUFFIXES

    found: dict[str, Path] = {}
    for path in sorted(folder.iterdir()):
        suffix = path.suffix.lower()
        if path.name.startswith(".") or suffix not in (*ASCII_SUFFIXES, *_EMBEDDED_SUFFIXES):
            continue
        if suffix == ".cache" and not path.is_dir():
            continue
        if path.stem in found:
            raise TrainingDataError(
                f"{folder}: two scans named {path.stem!r} ({found[path.stem].name}, "
                f"{path.name}): expected one file per scan"
            )
        found[path.stem] = path
    return found


def _registry_scans(folder: Path, split: str) -> dict[str, Path]:
    from semantic3d.datasets.semantic3d import Semantic3D

    return {
        files.scan.name: files.points_path
        for files in Semantic3D(folder).scans(split)
        if files.has_points
    }


def _with_labels(points: Path, name: str) -> LabelledScan:
    from semantic3d.io.formats import ASCII_SUFFIXES, iter_points, sibling_labels_path

    if points.suffix.lower() in ASCII_SUFFIXES:
        labels = sibling_labels_path(points)
        if labels is None:
            raise TrainingDataError(
                f"{points}: training needs labels: expected {points.with_suffix('.labels').name} "
                "beside it"
            )
        return LabelledScan(name, points, labels)
    first = next(iter(iter_points(points, chunk_size=1)), None)
    if first is None or first.labels is None:
        raise TrainingDataError(
            f"{points}: training needs labels: expected a label column in the file, found none"
        )
    return LabelledScan(name, points, None)
