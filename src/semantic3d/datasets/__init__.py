"""The benchmark's scans, splits and submission names; downloading them; a dataset folder view.

Importing this package does not import ``py7zr``; extraction imports it on first use (extra
``download``).
"""

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
    ArchiveFile,
    ScanInfo,
    Split,
    UnknownScanError,
    scan,
    scans,
    submission_name,
)
from semantic3d.datasets.semantic3d import ScanFiles, Semantic3D

__all__ = [
    "DEFAULT_BASE_URL",
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
    "scan",
    "scans",
    "submission_name",
]
