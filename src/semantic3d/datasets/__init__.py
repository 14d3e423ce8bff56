"""The benchmark's scans, splits and submission names; downloading them; a dataset folder view.

Importing this package does not import ``py7zr``; extraction imports it on first use (extra
``download``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.datasets.download import (
        DownloadProgress,
        DownloadReport,
        IncompleteDownloadError,
        ScanDownload,
        download_file,
        download_scans,
        download_split,
    )
    from semantic3d.datasets.registry import (
        DEFAULT_BASE_URL,
        REFERENCE_FOLDS,
        REFERENCE_VALIDATION_FOLD,
        ArchiveFile,
        ScanInfo,
        Split,
        UnknownScanError,
        reference_split,
        scan,
        scans,
        submission_name,
    )
    from semantic3d.datasets.semantic3d import ScanFiles, Semantic3D

__all__ = [
    "DEFAULT_BASE_URL",
    "REFERENCE_FOLDS",
    "REFERENCE_VALIDATION_FOLD",
    "ArchiveFile",
    "DownloadProgress",
    "DownloadReport",
    "IncompleteDownloadError",
    "ScanDownload",
    "ScanFiles",
    "ScanInfo",
    "Semantic3D",
    "Split",
    "UnknownScanError",
    "download_file",
    "download_scans",
    "download_split",
    "reference_split",
    "scan",
    "scans",
    "submission_name",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "DEFAULT_BASE_URL": "semantic3d.datasets.registry",
        "REFERENCE_FOLDS": "semantic3d.datasets.registry",
        "REFERENCE_VALIDATION_FOLD": "semantic3d.datasets.registry",
        "ArchiveFile": "semantic3d.datasets.registry",
        "DownloadProgress": "semantic3d.datasets.download",
        "DownloadReport": "semantic3d.datasets.download",
        "IncompleteDownloadError": "semantic3d.datasets.download",
        "ScanDownload": "semantic3d.datasets.download",
        "ScanFiles": "semantic3d.datasets.semantic3d",
        "ScanInfo": "semantic3d.datasets.registry",
        "Semantic3D": "semantic3d.datasets.semantic3d",
        "Split": "semantic3d.datasets.registry",
        "UnknownScanError": "semantic3d.datasets.registry",
        "download_file": "semantic3d.datasets.download",
        "download_scans": "semantic3d.datasets.download",
        "download_split": "semantic3d.datasets.download",
        "reference_split": "semantic3d.datasets.registry",
        "scan": "semantic3d.datasets.registry",
        "scans": "semantic3d.datasets.registry",
        "submission_name": "semantic3d.datasets.registry",
    },
)
