"""``FeatureConfig``: the settings of the multi-scale feature stage.

The ``[features]`` table of a configuration file (see :mod:`semantic3d.core.config`);
:class:`ConfigError` is the core one, re-exported here where it has always been.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

from semantic3d.core.errors import ConfigError
from semantic3d.features.names import CYLINDER_FEATURES, column_names, level_feature_names

__all__ = ["MAX_LEVELS", "ConfigError", "FeatureConfig"]

MAX_LEVELS = 16


@dataclass(frozen=True, slots=True)
class FeatureConfig:
    """Settings of the voxel pyramid and its k-nearest-neighbour features (Hackel et al. 2016).

    Attributes:
        base_voxel_size_m: voxel size of the finest pyramid level; level ``l`` has voxels of
            ``base_voxel_size_m * 2**l``.
        n_levels: number of pyramid levels.
        k_neighbours: neighbours per query at every level (the query's own voxel included).
        per_point: False (default): each point takes the features of its voxel at every
            level (features computed once per voxel). True: every full-resolution point is
            a query of its own at every level (Hackel et al. 2016 as we read it; the
            semantic3D.net paper does not say; ~n_levels times the k-NN work at full
            resolution).
        colour: add HSV of the mean neighbourhood colour per level.
        intensity: add the mean neighbourhood intensity per level.
        spherical_height: the height range, height below and above over the k nearest
            neighbours per level (``vertical_range``, ``height_below``, ``height_above``).
        cylinders: height features of vertical cylinders per level (the paper's "height
            features based on vertical, cylindrical neighbourhoods"; the columns are ours:
            ``cylinder_range``, ``cylinder_below``, ``cylinder_above``, ``cylinder_points``;
            :mod:`~semantic3d.features.cylinders`).
        cylinder_radius_voxels: cylinder radius in voxel sizes of its level (the radius
            doubles with the voxel size).
        cylinder_features: which cylinder columns to keep, in
            :data:`~semantic3d.features.names.CYLINDER_FEATURES` order. Default: only
            ``cylinder_below`` (the height above the lowest point around), the one that
            generalised to scans left out of training (docs/baseline_covariance.md); the
            paper preset keeps all four.
    """

    base_voxel_size_m: float = 0.025
    n_levels: int = 9
    k_neighbours: int = 10
    per_point: bool = False
    colour: bool = False
    intensity: bool = False
    spherical_height: bool = True
    cylinders: bool = True
    cylinder_radius_voxels: float = 2.0
    cylinder_features: tuple[str, ...] = ("cylinder_below",)

    def __post_init__(self) -> None:
        if not 0.0 < self.base_voxel_size_m < 1e3:
            raise ConfigError(
                f"base_voxel_size_m: expected a size in metres in (0, 1000), "
                f"found {self.base_voxel_size_m}"
            )
        if not _is_integer(self.n_levels) or not 1 <= self.n_levels <= MAX_LEVELS:
            raise ConfigError(f"n_levels: expected 1..{MAX_LEVELS}, found {self.n_levels!r}")
        if not _is_integer(self.k_neighbours) or not 3 <= self.k_neighbours <= 256:
            raise ConfigError(f"k_neighbours: expected 3..256, found {self.k_neighbours!r}")
        if not self.cylinder_features or tuple(
            name for name in CYLINDER_FEATURES if name in self.cylinder_features
        ) != tuple(self.cylinder_features):
            raise ConfigError(
                f"cylinder_features: expected some of {list(CYLINDER_FEATURES)} in that "
                f"order, found {list(self.cylinder_features)}"
            )
        if not 0.0 < self.cylinder_radius_voxels <= 64.0:
            raise ConfigError(
                f"cylinder_radius_voxels: expected a radius in (0, 64] voxel sizes, "
                f"found {self.cylinder_radius_voxels}"
            )

    @property
    def voxel_sizes_m(self) -> tuple[float, ...]:
        """Voxel size of every level, finest first."""
        return tuple(self.base_voxel_size_m * 2**level for level in range(self.n_levels))

    @property
    def coarsest_voxel_size_m(self) -> float:
        """Voxel size of the coarsest level."""
        return self.base_voxel_size_m * 2 ** (self.n_levels - 1)

    @property
    def level_feature_names(self) -> tuple[str, ...]:
        """Feature names computed at every level, in column order."""
        return level_feature_names(
            colour=self.colour,
            intensity=self.intensity,
            spherical_height=self.spherical_height,
            cylinders=self.cylinder_features if self.cylinders else (),
        )

    @property
    def feature_names(self) -> tuple[str, ...]:
        """All column names (``planarity@0.100m``), level-major."""
        return column_names(
            self.voxel_sizes_m,
            colour=self.colour,
            intensity=self.intensity,
            spherical_height=self.spherical_height,
            cylinders=self.cylinder_features if self.cylinders else (),
        )

    def cylinder_radius_m(self, level: int) -> float:
        """Horizontal radius of the cylinders of pyramid level ``level``."""
        return self.cylinder_radius_voxels * self.base_voxel_size_m * 2**level

    @property
    def n_features(self) -> int:
        """Number of feature columns."""
        return self.n_levels * len(self.level_feature_names)


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)
