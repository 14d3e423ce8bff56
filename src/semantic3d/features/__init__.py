"""Multi-scale geometric features: voxel pyramid, k-NN neighbourhoods, named columns.

The feature set of Hackel, Wegner & Schindler (2016), "Fast semantic segmentation of 3D
point clouds with strongly varying density": a voxel pyramid whose voxel size doubles per
level, a constant k nearest neighbours per level, covariance / moment / height features
per level, named ``<feature>@<voxel size>m``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.features.config import ConfigError, FeatureConfig
    from semantic3d.features.multiscale import (
        FeatureTable,
        build_cloud_pyramid,
        compute_level_features,
        compute_multiscale_features,
    )
    from semantic3d.features.names import (
        GEOMETRIC_FEATURES,
        column_name,
        column_names,
        parse_column_name,
    )
    from semantic3d.features.pyramid import (
        ExtentError,
        PyramidLevel,
        VoxelPyramid,
        build_pyramid,
        grid_origin,
    )
    from semantic3d.features.scan import FeatureBlock, iter_scan_features
    from semantic3d.features.tiling import TiledScan, TileFeatures

__all__ = [
    "GEOMETRIC_FEATURES",
    "ConfigError",
    "ExtentError",
    "FeatureBlock",
    "FeatureConfig",
    "FeatureTable",
    "PyramidLevel",
    "TileFeatures",
    "TiledScan",
    "VoxelPyramid",
    "build_cloud_pyramid",
    "build_pyramid",
    "column_name",
    "column_names",
    "compute_level_features",
    "compute_multiscale_features",
    "grid_origin",
    "iter_scan_features",
    "parse_column_name",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "GEOMETRIC_FEATURES": "semantic3d.features.names",
        "ConfigError": "semantic3d.features.config",
        "ExtentError": "semantic3d.features.pyramid",
        "FeatureBlock": "semantic3d.features.scan",
        "FeatureConfig": "semantic3d.features.config",
        "FeatureTable": "semantic3d.features.multiscale",
        "PyramidLevel": "semantic3d.features.pyramid",
        "TileFeatures": "semantic3d.features.tiling",
        "TiledScan": "semantic3d.features.tiling",
        "VoxelPyramid": "semantic3d.features.pyramid",
        "build_cloud_pyramid": "semantic3d.features.multiscale",
        "build_pyramid": "semantic3d.features.pyramid",
        "column_name": "semantic3d.features.names",
        "column_names": "semantic3d.features.names",
        "compute_level_features": "semantic3d.features.multiscale",
        "compute_multiscale_features": "semantic3d.features.multiscale",
        "grid_origin": "semantic3d.features.pyramid",
        "iter_scan_features": "semantic3d.features.scan",
        "parse_column_name": "semantic3d.features.names",
    },
)
