"""Points per class per split: the paper's class statistics (its Figure 5(a), Section 6)
of a labels folder.

Every ``.labels`` file of a folder is streamed once (constant memory) and its label values
counted. A file whose stem is a benchmark scan (``semantic3d.datasets.registry``) is
grouped under that scan's split (``train``, ``semantic-8``, ``reduced-8``); any other file
under ``custom``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.classes import CLASSES, N_CLASSES
from semantic3d.core.errors import DataFormatError
from semantic3d.datasets.registry import UnknownScanError
from semantic3d.datasets.registry import scan as registry_scan
from semantic3d.io.labels import iter_labels

CUSTOM_SPLIT = "custom"
"""The split of label files that are not benchmark scans."""

ScanProgress = Callable[[int, int], None]
"""``progress(done_bytes, total_bytes)`` over every file of the folder."""


@dataclass(frozen=True, slots=True)
class ScanClassCounts:
    """Label-value counts of one ``.labels`` file.

    Attributes:
        name: the file stem.
        split: the scan's split, or ``"custom"``.
        counts: ``(N_CLASSES + 1,)`` int64: index ``v`` counts label value ``v`` (0 unlabelled).
    """

    name: str
    split: str
    path: Path
    counts: NDArray[np.int64]

    @property
    def n_points(self) -> int:
        """All lines of the file, unlabelled included."""
        return int(self.counts.sum())


@dataclass(frozen=True, slots=True)
class ClassStatistics:
    """Counts of every scan of a folder, and their sums per split."""

    scans: tuple[ScanClassCounts, ...]

    @property
    def splits(self) -> tuple[str, ...]:
        """Splits present, in first-seen order."""
        return tuple(dict.fromkeys(s.split for s in self.scans))

    def counts_by_split(self) -> dict[str, NDArray[np.int64]]:
        """Split -> ``(N_CLASSES + 1,)`` counts by label value (index 0: unlabelled)."""
        totals: dict[str, NDArray[np.int64]] = {}
        for scan in self.scans:
            if scan.split not in totals:
                totals[scan.split] = np.zeros(N_CLASSES + 1, np.int64)
            totals[scan.split] += scan.counts
        return totals

    def class_counts_by_split(self) -> dict[str, NDArray[np.int64]]:
        """Split -> ``(N_CLASSES,)`` counts by class index (unlabelled dropped), for plots."""
        return {split: counts[1:] for split, counts in self.counts_by_split().items()}


def split_of(scan_name: str) -> str:
    """The benchmark split of a scan file stem or registry name, else ``"custom"``."""
    try:
        return str(registry_scan(scan_name).split.value)
    except UnknownScanError:
        return CUSTOM_SPLIT


def count_label_values(path: Path) -> NDArray[np.int64]:
    """``(N_CLASSES + 1,)`` counts of label values 0..8 in a ``.labels`` file (streamed)."""
    counts = np.zeros(N_CLASSES + 1, np.int64)
    for chunk in iter_labels(path):
        binned = np.bincount(chunk, minlength=N_CLASSES + 1)
        if binned.shape[0] > N_CLASSES + 1:
            bad = int(np.flatnonzero(binned[N_CLASSES + 1 :])[0]) + N_CLASSES + 1
            raise DataFormatError(
                f"expected label values 0..{N_CLASSES}, found {bad}", path=str(path)
            )
        counts += binned
    return counts


def compute_class_statistics(
    folder: Path,
    *,
    splits: Mapping[str, str] | None = None,
    progress: ScanProgress | None = None,
) -> ClassStatistics:
    """Count label values of every ``*.labels`` file under ``folder`` (recursively).

    Hidden files (``._x.labels`` left by macOS, partial writes) are skipped.

    Args:
        folder: a folder of ``.labels`` files.
        splits: optional file stem -> split overrides; other stems are looked up in the
            benchmark registry, then fall back to ``"custom"``.
        progress: called with bytes read so far and in all, after each file.
    """
    if not folder.is_dir():
        raise DataFormatError(f"expected a folder of .labels files, found {folder}")
    files = sorted(
        p for p in folder.rglob("*.labels") if not p.name.startswith(".") and p.is_file()
    )
    if not files:
        raise DataFormatError(f"{folder}: expected at least one *.labels file, found none")
    total = sum(p.stat().st_size for p in files)
    done = 0
    scans = []
    for path in files:
        split = (splits or {}).get(path.stem) or split_of(path.stem)
        scans.append(ScanClassCounts(path.stem, split, path, count_label_values(path)))
        done += path.stat().st_size
        if progress is not None:
            progress(done, total)
    return ClassStatistics(tuple(scans))


def class_table(statistics: ClassStatistics) -> tuple[list[str], list[list[str]]]:
    """Header and rows: points per class (and unlabelled, and total) for each split."""
    header = ["Split", "Scans", "unlabelled", *(c.name for c in CLASSES), "total"]
    by_split = statistics.counts_by_split()
    rows = []
    for split, counts in by_split.items():
        n_scans = sum(1 for s in statistics.scans if s.split == split)
        rows.append([split, str(n_scans), *(str(int(v)) for v in counts), str(int(counts.sum()))])
    return header, rows
