"""Safe 7z extraction: chosen members, streamed to disk, landed under their final names atomically.

py7zr decompresses each member block by block straight into its output file (it never holds
a whole member in memory), so multi-gigabyte scans extract in bounded memory. What this
module adds is the policy around it: refuse archives whose member names could escape the
target folder, check free disk space first, extract into a temporary folder on the target's
filesystem, then ``Path.replace`` (an atomic rename) each file to its final name, so a final name only ever holds
a complete file.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from semantic3d.core.errors import DownloadError, require

__all__ = ["check_member_name", "extract_members"]

logger = logging.getLogger(__name__)

# Room left on the disk after extraction, on top of the members' sizes.
_DISK_MARGIN_BYTES = 64 << 20


def check_member_name(name: str, *, archive: Path | str) -> None:
    """Raise :class:`DownloadError` when an archive member name could leave the target folder.

    Refused: absolute paths (POSIX or Windows, drive letters included), any ``..`` part, and
    empty names.

    >>> check_member_name("scan.txt", archive="a.7z")
    >>> check_member_name("../scan.txt", archive="a.7z")
    Traceback (most recent call last):
    ...
    semantic3d.core.errors.DownloadError: a.7z: unsafe member '../scan.txt': expected a relative path inside the archive, found a path that leaves it
    """
    posix, windows = PurePosixPath(name), PureWindowsPath(name)
    unsafe = (
        not name.strip()
        or posix.is_absolute()
        or windows.is_absolute()
        or bool(windows.drive)
        or name.startswith(("/", "\\"))
        or ".." in posix.parts
        or ".." in windows.parts
    )
    if unsafe:
        raise DownloadError(
            f"{archive}: unsafe member {name!r}: expected a relative path inside the archive, "
            "found a path that leaves it"
        )


def _open_archive(path: Path) -> Any:
    py7zr: Any = require("py7zr", "download")
    try:
        return py7zr.SevenZipFile(path, mode="r")
    # Downloaded bytes are untrusted: a corrupt header can surface as any decoding error.
    except Exception as exc:
        raise DownloadError(f"{path.name}: not a readable 7z archive: {exc}") from exc


def extract_members(archive: Path, members: Mapping[str, Path]) -> list[Path]:
    """Extract ``members`` (member name -> final path) from the 7z file ``archive``.

    Every member name in the archive is checked first (see :func:`check_member_name`); a
    symbolic link or an unsafe name anywhere refuses the whole archive. Files are extracted
    into a temporary folder beside each final path and moved into place with ``Path.replace`` (an atomic rename);
    nothing is left under a final name when extraction fails. Returns the final paths.
    """
    if not members:
        return []
    with _open_archive(archive) as handle:
        entries = {entry.filename: entry for entry in handle.list()}
        for name, entry in entries.items():
            check_member_name(name, archive=archive.name)
            if entry.is_symlink:
                raise DownloadError(
                    f"{archive.name}: unsafe member {name!r}: expected a regular file, "
                    "found a symbolic link"
                )
        missing = sorted(set(members) - set(entries))
        if missing:
            found = ", ".join(sorted(entries)) or "nothing"
            raise DownloadError(
                f"{archive.name}: expected member(s) {', '.join(missing)}, found {found}"
            )
        targets = {name: Path(path) for name, path in members.items()}
        parents = {path.parent for path in targets.values()}
        if len(parents) != 1:
            raise DownloadError(f"{archive.name}: expected one output folder, found {len(parents)}")
        out_dir = parents.pop()
        out_dir.mkdir(parents=True, exist_ok=True)
        _check_disk_space(
            out_dir, sum(int(entries[name].uncompressed or 0) for name in targets), archive
        )
        scratch = Path(tempfile.mkdtemp(prefix=".extract-", dir=out_dir))
        try:
            logger.info("extracting %s from %s", ", ".join(targets), archive.name)
            try:
                handle.extract(path=scratch, targets=list(targets))
            # Corrupt or hostile data can fail in any decoder (CRC, LZMA, BCJ, zlib, struct).
            except Exception as exc:
                raise DownloadError(f"{archive.name}: extraction failed: {exc}") from exc
            for name in targets:
                produced = scratch / name
                if not produced.is_file():
                    raise DownloadError(f"{archive.name}: member {name!r} did not extract")
            landed = []
            for name, final in targets.items():
                (scratch / name).replace(final)
                landed.append(final)
            return landed
        finally:
            shutil.rmtree(scratch, ignore_errors=True)


def _check_disk_space(folder: Path, needed_bytes: int, archive: Path) -> None:
    free = shutil.disk_usage(folder).free
    if needed_bytes + _DISK_MARGIN_BYTES > free:
        raise DownloadError(
            f"{archive.name}: extracting needs {needed_bytes / 1e9:.2f} GB in {folder}, "
            f"found {free / 1e9:.2f} GB free"
        )
