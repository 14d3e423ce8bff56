"""``Semantic3D(root)``: which benchmark scans a folder holds, where their files are, what is missing.

The folder layout is the one :func:`~semantic3d.datasets.download.download_split` writes
(and the one Open3D-ML, KPConv and RandLA-Net read): every scan's ``<stem>.txt`` and, for
training scans, ``<stem>.labels`` side by side in one folder.

>>> from pathlib import Path
>>> dataset = Semantic3D(Path("/nonexistent"))
>>> len(dataset.missing("reduced-8"))
4
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from semantic3d.datasets.registry import ScanInfo, Split, scan, scans

__all__ = ["ScanFiles", "Semantic3D"]


@dataclass(frozen=True, slots=True)
class ScanFiles:
    """A scan's files under a dataset folder, with their sizes at the time of the look-up.

    ``labels_path`` is ``None`` for test scans (no public ground truth); a size is ``None``
    when the file is absent.
    """

    scan: ScanInfo
    points_path: Path
    labels_path: Path | None
    points_bytes: int | None
    labels_bytes: int | None

    @property
    def has_points(self) -> bool:
        """Whether the points file is present."""
        return self.points_bytes is not None

    @property
    def has_labels(self) -> bool:
        """Whether the ground-truth labels file is present (never for test scans)."""
        return self.labels_bytes is not None

    @property
    def complete(self) -> bool:
        """Whether every file of the scan (points, and labels where the benchmark has them)."""
        return self.has_points and (self.labels_path is None or self.has_labels)

    @property
    def size_bytes(self) -> int:
        """Bytes on disk of the files present."""
        return (self.points_bytes or 0) + (self.labels_bytes or 0)


def _size(path: Path) -> int | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_size if path.is_file() else None


class Semantic3D:
    """A read-only view of a folder holding (some of) the benchmark's scans.

    Every call looks at the disk again, so the view follows downloads as they land.
    """

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"Semantic3D({str(self.root)!r})"

    def paths(self, name: str) -> ScanFiles:
        """The files of scan ``name`` (registry name or file stem) under this folder."""
        info = scan(name)
        points_path = self.root / info.points.filename
        labels_path = None if info.labels is None else self.root / info.labels.filename
        return ScanFiles(
            scan=info,
            points_path=points_path,
            labels_path=labels_path,
            points_bytes=_size(points_path),
            labels_bytes=None if labels_path is None else _size(labels_path),
        )

    def scans(self, split: Split | str | None = None) -> tuple[ScanFiles, ...]:
        """Every registry scan of ``split`` (all when ``None``), present or not."""
        return tuple(self.paths(info.name) for info in scans(split))

    def present(self, split: Split | str | None = None) -> tuple[ScanFiles, ...]:
        """The scans of ``split`` whose files are all here."""
        return tuple(files for files in self.scans(split) if files.complete)

    def missing(self, split: Split | str | None = None) -> tuple[ScanInfo, ...]:
        """The scans of ``split`` with at least one file absent."""
        return tuple(files.scan for files in self.scans(split) if not files.complete)

    def is_complete(self, split: Split | str | None = None) -> bool:
        """Whether every scan of ``split`` is here."""
        return not self.missing(split)
