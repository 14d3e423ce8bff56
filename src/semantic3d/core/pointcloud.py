"""``PointCloud``: a struct of arrays, the unit of data moving between layers."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError


@dataclass(frozen=True, slots=True)
class PointCloud:
    """Points of one scan (or one chunk of it) as parallel arrays.

    Attributes:
        xyz: ``(n, 3)`` float64 coordinates in metres (georeferenced values keep
            millimetres: float64 holds 870 000.001 exactly enough).
        intensity: ``(n,)`` int32 intensities as the scanner wrote them (Semantic3D
            files carry signed values such as ``-1515``).
        rgb: ``(n, 3)`` uint8 colours.
        labels: optional ``(n,)`` uint8 label values (0 unlabelled, 1..8 classes).
    """

    xyz: NDArray[np.float64]
    intensity: NDArray[np.int32]
    rgb: NDArray[np.uint8]
    labels: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        xyz, intensity, rgb, labels = self.xyz, self.intensity, self.rgb, self.labels
        if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.dtype != np.float64:
            raise ShapeError(
                f"xyz: expected an (n, 3) float64 array, found {xyz.shape} {xyz.dtype}"
            )
        n = xyz.shape[0]
        if intensity.shape != (n,) or intensity.dtype != np.int32:
            raise ShapeError(
                f"intensity: expected ({n},) int32, found {intensity.shape} {intensity.dtype}"
            )
        if rgb.shape != (n, 3) or rgb.dtype != np.uint8:
            raise ShapeError(f"rgb: expected ({n}, 3) uint8, found {rgb.shape} {rgb.dtype}")
        if labels is not None and (labels.shape != (n,) or labels.dtype != np.uint8):
            raise ShapeError(f"labels: expected ({n},) uint8, found {labels.shape} {labels.dtype}")

    @classmethod
    def from_arrays(
        cls,
        xyz: ArrayLike,
        *,
        intensity: ArrayLike | None = None,
        rgb: ArrayLike | None = None,
        labels: ArrayLike | None = None,
    ) -> PointCloud:
        """Build a cloud from array-likes, converting dtypes; missing columns become zeros."""
        xyz_arr = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64).reshape(-1, 3))
        n = xyz_arr.shape[0]
        intensity_arr = (
            np.zeros(n, np.int32) if intensity is None else np.asarray(intensity).astype(np.int32)
        )
        rgb_arr = np.zeros((n, 3), np.uint8) if rgb is None else np.asarray(rgb).astype(np.uint8)
        labels_arr = None if labels is None else np.asarray(labels).astype(np.uint8)
        return cls(xyz_arr, intensity_arr, rgb_arr.reshape(-1, 3), labels_arr)

    @classmethod
    def empty(cls, *, with_labels: bool = False) -> PointCloud:
        """A cloud with no points."""
        return cls(
            np.empty((0, 3), np.float64),
            np.empty(0, np.int32),
            np.empty((0, 3), np.uint8),
            np.empty(0, np.uint8) if with_labels else None,
        )

    @classmethod
    def concatenate(cls, clouds: Sequence[PointCloud]) -> PointCloud:
        """Join clouds end to end; labels are kept only when every part has them."""
        if not clouds:
            return cls.empty()
        has_labels = all(c.labels is not None for c in clouds)
        return cls(
            np.concatenate([c.xyz for c in clouds]),
            np.concatenate([c.intensity for c in clouds]),
            np.concatenate([c.rgb for c in clouds]),
            np.concatenate([c.labels for c in clouds if c.labels is not None])
            if has_labels
            else None,
        )

    @property
    def n_points(self) -> int:
        """Number of points."""
        return int(self.xyz.shape[0])

    def __len__(self) -> int:
        return self.n_points

    def __getitem__(self, index: slice | NDArray[np.integer] | NDArray[np.bool_]) -> PointCloud:
        """The points selected by a slice, an index array or a boolean mask."""
        return PointCloud(
            self.xyz[index],
            self.intensity[index],
            self.rgb[index],
            None if self.labels is None else self.labels[index],
        )

    def with_labels(self, labels: ArrayLike | None) -> PointCloud:
        """A copy sharing the point arrays, with ``labels`` attached (or removed with None)."""
        arr = None if labels is None else np.asarray(labels).astype(np.uint8, copy=False)
        return PointCloud(self.xyz, self.intensity, self.rgb, arr)

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(min_xyz, max_xyz)``; raises :class:`ShapeError` on an empty cloud."""
        if self.n_points == 0:
            raise ShapeError("bounds of an empty point cloud are undefined")
        return self.xyz.min(axis=0), self.xyz.max(axis=0)

    def equals(self, other: PointCloud) -> bool:
        """True when every array is equal (labels compared too)."""
        if (self.labels is None) != (other.labels is None):
            return False
        same = (
            np.array_equal(self.xyz, other.xyz)
            and np.array_equal(self.intensity, other.intensity)
            and np.array_equal(self.rgb, other.rgb)
        )
        if self.labels is not None and other.labels is not None:
            same = same and np.array_equal(self.labels, other.labels)
        return bool(same)
