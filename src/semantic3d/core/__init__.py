"""Core values shared by every layer: errors, the class map, the point cloud and the
configuration loader (:mod:`semantic3d.core.config`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.core.classes import (
        CLASSES,
        LABEL_VALUES,
        N_CLASSES,
        UNLABELLED,
        SemanticClass,
        class_by_name,
        class_by_value,
        label_palette,
    )
    from semantic3d.core.errors import (
        ConfigError,
        DataFormatError,
        DownloadError,
        MissingExtraError,
        Semantic3DError,
        ShapeError,
        SubmissionError,
    )
    from semantic3d.core.pointcloud import PointCloud

__all__ = [
    "CLASSES",
    "LABEL_VALUES",
    "N_CLASSES",
    "UNLABELLED",
    "ConfigError",
    "DataFormatError",
    "DownloadError",
    "MissingExtraError",
    "PointCloud",
    "Semantic3DError",
    "SemanticClass",
    "ShapeError",
    "SubmissionError",
    "class_by_name",
    "class_by_value",
    "label_palette",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "CLASSES": "semantic3d.core.classes",
        "LABEL_VALUES": "semantic3d.core.classes",
        "N_CLASSES": "semantic3d.core.classes",
        "UNLABELLED": "semantic3d.core.classes",
        "ConfigError": "semantic3d.core.errors",
        "DataFormatError": "semantic3d.core.errors",
        "DownloadError": "semantic3d.core.errors",
        "MissingExtraError": "semantic3d.core.errors",
        "PointCloud": "semantic3d.core.pointcloud",
        "Semantic3DError": "semantic3d.core.errors",
        "SemanticClass": "semantic3d.core.classes",
        "ShapeError": "semantic3d.core.errors",
        "SubmissionError": "semantic3d.core.errors",
        "class_by_name": "semantic3d.core.classes",
        "class_by_value": "semantic3d.core.classes",
        "label_palette": "semantic3d.core.classes",
    },
)
