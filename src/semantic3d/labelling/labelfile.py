"""Reading a scan's ``.labels`` file for labelling or viewing, checked against the scan.

A labels file must hold exactly one value per point of the scan, each a label value
0..8; anything else is refused with :class:`~semantic3d.labelling.errors.LabelFileError`
before the session opens, so nothing (journal, saved file) is written from bad input.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.classes import N_CLASSES
from semantic3d.core.errors import DataFormatError
from semantic3d.io.cache import CachedScan, is_cache_current, open_cache
from semantic3d.io.conversion import build_cache
from semantic3d.io.formats import PointFormat, detect_format
from semantic3d.labelling.cachedir import entry_name
from semantic3d.labelling.errors import LabelFileError

__all__ = ["build_cache_if_needed", "read_label_file"]


def read_label_file(path: Path, *, n_points: int) -> NDArray[np.uint8]:
    """The labels of ``path``, one per point of a scan of ``n_points`` points.

    Raises:
        LabelFileError: a line that is not a label value, a value above 8, or a number of
            lines other than ``n_points``.
    """
    from semantic3d.io.labels import iter_labels

    labels = np.empty(n_points, np.uint8)
    filled = 0
    try:
        chunks = iter_labels(path)
        for chunk in chunks:
            if filled + chunk.size > n_points:
                filled += chunk.size + sum(more.size for more in chunks)
                raise LabelFileError(
                    f"expected {n_points} labels (one per point of the scan), found {filled}",
                    path=str(path),
                )
            bad = np.flatnonzero(chunk > N_CLASSES)
            if bad.size:
                raise LabelFileError(
                    f"expected label values 0..{N_CLASSES}, found {int(chunk[bad[0]])}",
                    path=str(path),
                    line=filled + int(bad[0]) + 1,
                )
            labels[filled : filled + chunk.size] = chunk
            filled += chunk.size
    except LabelFileError:
        raise
    except DataFormatError as exc:
        raise LabelFileError(exc.detail, path=exc.path, line=exc.line) from None
    if filled != n_points:
        raise LabelFileError(
            f"expected {n_points} labels (one per point of the scan), found {filled}",
            path=str(path),
        )
    return labels


def build_cache_if_needed(
    scan_path: str | Path,
    *,
    cache_dir: Path,
    progress: Callable[[str, int, int], None] | None = None,
) -> CachedScan:
    """The cache of ``scan_path``, built under ``cache_dir`` and never beside the scan.

    A cache folder is opened as it is. For a point file, a current ``NAME.cache`` the user
    built beside it is read (not written); otherwise the cache lives in ``cache_dir``
    under a name keyed by the file's resolved path, and is rebuilt when the file changes.
    """
    path = Path(scan_path)
    if detect_format(path) is PointFormat.CACHE:
        return open_cache(path)
    if not path.is_file():
        raise DataFormatError(
            "expected a point file or a cache folder, found nothing", path=str(path)
        )

    def report(done: int, total: int) -> None:
        if progress is not None:
            progress("cache", done, total)

    beside = path.with_suffix(".cache")
    if beside.is_dir() and is_cache_current(beside, path):
        return open_cache(beside)
    cache_dir.mkdir(parents=True, exist_ok=True)
    return build_cache(path, cache_dir / f"{entry_name(path)}.cache", progress=report)
