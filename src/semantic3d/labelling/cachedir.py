"""Where the labelling app keeps its caches: a per-user cache folder, never beside the data.

A scan folder may be read-only or shared, and a 50 M-point cache weighs gigabytes, so
``label`` and ``view`` write nothing beside the scan. The binary cache of a point file and
the level-of-detail index of any cache live under one cache folder: ``--cache-dir``, else
``$SEMANTIC3D_CACHE_DIR``, else the per-user cache folder of the platform
(``platformdirs.user_cache_dir``, e.g. ``~/.cache/semantic3d`` on Linux).

Entries are keyed by the scan's resolved path (``NAME-<16 hex>``), so two scans with the same
name in different folders never share an entry; a changed scan (size or modification
time) or a rebuilt cache is rebuilt in place (:func:`semantic3d.io.build_cache` and
:func:`semantic3d.labelling.lod.open_lod` check their sources).

>>> key = entry_name(Path("/data/a/scan.txt"))
>>> key.startswith("scan-") and len(key) == len("scan-") + 16
True
>>> entry_name(Path("/data/a/scan.txt")) != entry_name(Path("/data/b/scan.txt"))
True
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["CACHE_DIR_ENV", "default_cache_dir", "entry_name", "resolve_cache_dir"]

CACHE_DIR_ENV = "SEMANTIC3D_CACHE_DIR"
"""Environment variable naming the cache folder (below ``--cache-dir``, above the default)."""


def default_cache_dir() -> Path:
    """``$SEMANTIC3D_CACHE_DIR`` or the platform's per-user cache folder for semantic3d."""
    configured = os.environ.get(CACHE_DIR_ENV)
    if configured:
        return Path(configured).expanduser()
    from semantic3d.core.errors import require

    require("platformdirs", "label")
    import platformdirs

    return Path(platformdirs.user_cache_dir("semantic3d", appauthor=False))


def resolve_cache_dir(cache_dir: str | Path | None) -> Path:
    """``cache_dir`` when given, else :func:`default_cache_dir`."""
    return default_cache_dir() if cache_dir is None else Path(cache_dir).expanduser()


def entry_name(path: Path) -> str:
    """``STEM-<hash of the resolved path>``: one entry per scan file, whatever its name."""
    resolved = str(Path(path).resolve())
    digest = hashlib.sha256(resolved.encode("utf-8", "surrogateescape")).hexdigest()[:16]
    stem = Path(path).name.split(".")[0] or "scan"
    return f"{stem}-{digest}"
