"""``meta.json`` of a binary cache: format version, point count, columns, source identity."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from semantic3d.core.errors import DataFormatError

__all__ = [
    "CACHE_FORMAT",
    "CACHE_FORMAT_VERSION",
    "COLUMNS",
    "META_FILE",
    "CacheMeta",
    "SourceInfo",
]

CACHE_FORMAT = "semantic3d-cache"
CACHE_FORMAT_VERSION = 1
META_FILE = "meta.json"

COLUMNS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "xyz": (np.dtype("<f8"), (3,)),
    "intensity": (np.dtype("<i4"), ()),
    "rgb": (np.dtype("u1"), (3,)),
    "labels": (np.dtype("u1"), ()),
}


@dataclass(frozen=True, slots=True)
class SourceInfo:
    """Identity of the file a cache was built from: a changed size or mtime means stale."""

    name: str
    size_bytes: int
    mtime_ns: int

    @classmethod
    def of(cls, path: str | Path) -> SourceInfo:
        """The identity of ``path`` as it is now."""
        stat = Path(path).stat()
        return cls(Path(path).name, int(stat.st_size), int(stat.st_mtime_ns))


@dataclass(frozen=True, slots=True)
class CacheMeta:
    """What ``meta.json`` records."""

    n_points: int
    has_labels: bool
    source: SourceInfo | None = None
    labels_source: SourceInfo | None = None
    version: int = CACHE_FORMAT_VERSION

    def to_dict(self) -> dict[str, Any]:
        """The JSON object written to ``meta.json``."""
        columns = {
            name: {
                "file": f"{name}.npy",
                "dtype": np.lib.format.dtype_to_descr(dtype),
                "shape": [self.n_points, *tail],
            }
            for name, (dtype, tail) in COLUMNS.items()
            if name != "labels" or self.has_labels
        }
        return {
            "format": CACHE_FORMAT,
            "version": self.version,
            "n_points": self.n_points,
            "has_labels": self.has_labels,
            "columns": columns,
            "source": None if self.source is None else _source_dict(self.source),
            "labels_source": None
            if self.labels_source is None
            else _source_dict(self.labels_source),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, path: str | None = None) -> CacheMeta:
        """Parse ``meta.json``; raises :class:`DataFormatError` on anything unexpected."""
        if not isinstance(data, dict) or data.get("format") != CACHE_FORMAT:
            found = data.get("format") if isinstance(data, dict) else type(data).__name__
            raise DataFormatError(f"expected format {CACHE_FORMAT!r}, found {found!r}", path=path)
        if data.get("version") != CACHE_FORMAT_VERSION:
            raise DataFormatError(
                f"expected cache format version {CACHE_FORMAT_VERSION}, found "
                f"{data.get('version')!r}: rebuild the cache",
                path=path,
            )
        n_points, has_labels = data.get("n_points"), data.get("has_labels")
        if not isinstance(n_points, int) or n_points < 0 or not isinstance(has_labels, bool):
            raise DataFormatError(
                f"expected a non-negative n_points and a boolean has_labels, found "
                f"{n_points!r} and {has_labels!r}",
                path=path,
            )
        try:
            source = _source_from(data.get("source"))
            labels_source = _source_from(data.get("labels_source"))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataFormatError(f"expected a source record, found {exc!r}", path=path) from exc
        return cls(n_points, has_labels, source, labels_source)


def _source_dict(source: SourceInfo) -> dict[str, Any]:
    return {"name": source.name, "size_bytes": source.size_bytes, "mtime_ns": source.mtime_ns}


def _source_from(data: Any) -> SourceInfo | None:
    if data is None:
        return None
    return SourceInfo(str(data["name"]), int(data["size_bytes"]), int(data["mtime_ns"]))
