"""Core values shared by every layer: errors, the class map and the point cloud."""

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
