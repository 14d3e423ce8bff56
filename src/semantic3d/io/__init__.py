"""Formats only: Semantic3D ASCII points and labels, LAS/LAZ, PLY and the binary cache.

Every reader streams: ``iter_*`` yields chunks, ``read_*`` wraps it, ``write_*`` takes
an iterable of chunks.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.io.ascii import (
        AsciiPointWriter,
        iter_ascii_points,
        open_ascii_writer,
        read_ascii_points,
        write_ascii_points,
    )
    from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, rechunk
    from semantic3d.io.conversion import build_cache
    from semantic3d.io.formats import (
        PointFormat,
        detect_format,
        iter_points,
        read_points,
        sibling_labels_path,
        write_points,
    )
    from semantic3d.io.labels import (
        attach_labels,
        count_labels,
        iter_labels,
        read_labels,
        write_labels,
    )
    from semantic3d.io.labelstream import LabelStream

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "AsciiPointWriter",
    "LabelStream",
    "PointFormat",
    "attach_labels",
    "build_cache",
    "count_labels",
    "detect_format",
    "iter_ascii_points",
    "iter_labels",
    "iter_points",
    "open_ascii_writer",
    "read_ascii_points",
    "read_labels",
    "read_points",
    "rechunk",
    "sibling_labels_path",
    "write_ascii_points",
    "write_labels",
    "write_points",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "DEFAULT_CHUNK_SIZE": "semantic3d.io.chunks",
        "AsciiPointWriter": "semantic3d.io.ascii",
        "LabelStream": "semantic3d.io.labelstream",
        "PointFormat": "semantic3d.io.formats",
        "attach_labels": "semantic3d.io.labels",
        "build_cache": "semantic3d.io.conversion",
        "count_labels": "semantic3d.io.labels",
        "detect_format": "semantic3d.io.formats",
        "iter_ascii_points": "semantic3d.io.ascii",
        "iter_labels": "semantic3d.io.labels",
        "iter_points": "semantic3d.io.formats",
        "open_ascii_writer": "semantic3d.io.ascii",
        "read_ascii_points": "semantic3d.io.ascii",
        "read_labels": "semantic3d.io.labels",
        "read_points": "semantic3d.io.formats",
        "rechunk": "semantic3d.io.chunks",
        "sibling_labels_path": "semantic3d.io.formats",
        "write_ascii_points": "semantic3d.io.ascii",
        "write_labels": "semantic3d.io.labels",
        "write_points": "semantic3d.io.formats",
    },
)
