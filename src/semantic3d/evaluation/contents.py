"""Opening a submission safely: a zip archive or a folder, its layout matched to a challenge.

Layout problems are collected, not raised: file names (case-sensitive, with a "did you
mean" hint), missing, extra, nested and duplicate files; one top-level folder tolerated;
``__MACOSX/``, ``.DS_Store`` and ``._*`` files ignored (in a folder, also the
``NAME.labels.json`` run records ``predict`` writes beside ``NAME.labels``). Archive safety: no absolute paths,
``..`` components or symbolic links; per-member and total uncompressed size caps and a
compression-ratio cap (zip bombs), enforced on the declared sizes before reading and on
the bytes actually inflated while streaming; the central directory is located and
walked as ``zipfile`` will (:mod:`semantic3d.evaluation.zipdirectory`), its member count
and size checked and any ambiguity refused *before* ``zipfile`` builds its index, so an
archive of a million empty entries costs milliseconds, not seconds and hundreds of
megabytes. Member
names are compared normalised (``d//a.labels`` is ``d/a.labels``). Members are streamed
(``zipfile.ZipFile.open``), never extracted.
"""

from __future__ import annotations

import difflib
import io
import os
import re
import stat
import zipfile
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import cast

from semantic3d.core.errors import SubmissionError
from semantic3d.evaluation.challenge import Challenge
from semantic3d.evaluation.zipdirectory import check_zip_directory
from semantic3d.evaluation.zipmember import INFLATE_ERRORS, open_member

_GIB = 1 << 30
_IGNORED_NAMES = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})
_ZIP_MAGIC = b"PK\x03\x04"
_READ_ERRORS: tuple[type[BaseException], ...] = (
    zipfile.BadZipFile,
    *INFLATE_ERRORS,
    EOFError,
    OSError,
    NotImplementedError,
    RuntimeError,
)


@dataclass(frozen=True, slots=True)
class SubmissionLimits:
    """Caps that keep a hostile archive from exhausting disk, memory or time.

    The largest semantic-8 scan has 430 M points: its labels take 0.9 GB (1.3 GB with
    CRLF line ends). Real label files deflate up to ~800:1 (long runs of one class) and
    deflate cannot exceed ~1030:1, so the ratio cap only rejects bzip2/LZMA bombs or
    forged headers; the size caps, also enforced on the bytes actually inflated, are the
    real defence.
    """

    max_member_bytes: int = 4 * _GIB
    max_total_bytes: int = 32 * _GIB
    max_compression_ratio: float = 2000.0
    ratio_check_min_bytes: int = 1 << 20
    max_members: int = 10_000
    max_directory_bytes: int = 16 << 20
    """Largest central directory (10,000 entries with 255-byte names take 3 MB)."""
    max_line_bytes: int = 16
    """Bytes a line of a label file takes at most on average (a value, spaces around it,
    CRLF): a file for a scan of ``n`` points is refused unread when it declares more than
    ``(n + 1) * max_line_bytes`` bytes, and never read past them."""


@dataclass(frozen=True, slots=True)
class SubmissionFile:
    """One label file of a submission, opened lazily as a binary stream."""

    name: str
    stored_name: str
    size: int
    opener: Callable[[], io.RawIOBase] | None = field(repr=False, compare=False)

    @property
    def rejected(self) -> bool:
        """True for a file found but refused unread (unsafe member, over a size cap)."""
        return self.opener is None

    def open(self, *, max_bytes: int | None = None) -> io.RawIOBase:
        """A fresh binary stream over the file's (uncompressed) bytes.

        ``max_bytes``: reading more than that many bytes raises (a
        :data:`READ_FAILURES` exception that :func:`read_failure` words).
        """
        if self.opener is None:
            raise ValueError(f"{self.name}: rejected file, not to be read")
        stream = self.opener()
        return stream if max_bytes is None else _CappedReader(stream, max_bytes)


@dataclass(slots=True)
class SubmissionContents:
    """The files of a submission matched to a challenge, and the layout problems found."""

    files: dict[str, SubmissionFile]
    problems: list[str]

    @property
    def total_bytes(self) -> int:
        """Uncompressed bytes of the matched files."""
        return sum(f.size for f in self.files.values())


class _LimitExceededError(Exception):
    pass


class _CappedReader(io.RawIOBase):
    """A read-only stream that fails once more than ``limit`` bytes came through."""

    def __init__(self, raw: io.RawIOBase | io.BufferedIOBase, limit: int) -> None:
        super().__init__()
        self._raw = raw
        self._left = limit
        self._limit = limit

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        got = self._raw.readinto(buffer) or 0
        self._left -= got
        if self._left < 0:
            raise _LimitExceededError(f"more than {self._limit} bytes once inflated")
        return got

    def close(self) -> None:
        self._raw.close()
        super().close()


def _is_ignored(parts: tuple[str, ...]) -> bool:
    return "__MACOSX" in parts or parts[-1] in _IGNORED_NAMES or parts[-1].startswith("._")


def _name_hint(name: str, candidates: list[str]) -> str:
    """A "did you mean" hint among the names still missing (compared without suffix)."""
    by_lower = {c.lower(): c for c in candidates}
    if name.lower() in by_lower:
        return f" (names are case-sensitive: did you mean {by_lower[name.lower()]!r}?)"
    stems = {PurePosixPath(c).stem: c for c in candidates}
    close = difflib.get_close_matches(PurePosixPath(name).stem, list(stems), n=1, cutoff=0.6)
    return f" (did you mean {stems[close[0]]!r}?)" if close else ""


def _strip_top_folder(
    entries: dict[str, SubmissionFile], problems: list[str]
) -> dict[str, SubmissionFile]:
    """Drop one top-level folder shared by every file; flag deeper layouts."""
    parts = {name: PurePosixPath(name).parts for name in entries}
    tops = {p[0] for p in parts.values() if len(p) > 1}
    strip = len(tops) == 1 and all(len(p) > 1 for p in parts.values())
    result: dict[str, SubmissionFile] = {}
    for name, entry in entries.items():
        rest = parts[name][1:] if strip else parts[name]
        if len(rest) != 1:
            problems.append(
                f"{name!r}: expected label files at the top level or inside one folder, "
                "found a nested path"
            )
            continue
        result[rest[0]] = SubmissionFile(rest[0], entry.stored_name, entry.size, entry.opener)
    return result


def _match_names(
    entries: dict[str, SubmissionFile], challenge: Challenge, problems: list[str]
) -> dict[str, SubmissionFile]:
    expected = list(challenge.submission_names)
    present = set(entries)
    missing = [name for name in expected if name not in present]
    for name in sorted(present - set(expected)):
        problems.append(f"unexpected file {name!r}{_name_hint(name, missing)}")
    scans = {scan.submission_name: scan for scan in challenge.scans}
    for name in missing:
        problems.append(f"missing file {name!r} (scan {scans[name].name})")
    return {
        name: entries[name] for name in expected if name in entries and not entries[name].rejected
    }


def _unsafe_path(name: str) -> str | None:
    """The problem with a member path that must not be used at all (None when safe)."""
    if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name):
        return f"{name!r}: absolute path (expected paths relative to the archive root)"
    if ".." in re.split(r"[/\\]", name):
        return f"{name!r}: path traversal ('..' component)"
    return None


def _zip_member_problems(info: zipfile.ZipInfo, limits: SubmissionLimits) -> list[str]:
    """Reasons to refuse reading a member (it still counts as present)."""
    name = info.filename
    found: list[str] = []
    if stat.S_ISLNK(info.external_attr >> 16):
        found.append(f"{name!r}: symbolic link (expected regular files)")
    if info.flag_bits & 0x1:
        found.append(f"{name!r}: encrypted member (expected plain label files)")
    if info.file_size > limits.max_member_bytes:
        found.append(
            f"{name!r}: uncompressed size {info.file_size} bytes exceeds the limit of "
            f"{limits.max_member_bytes} bytes"
        )
    if info.file_size >= limits.ratio_check_min_bytes:
        ratio = info.file_size / max(info.compress_size, 1)
        if ratio > limits.max_compression_ratio:
            found.append(
                f"{name!r}: compression ratio {ratio:.0f}:1 exceeds the limit of "
                f"{limits.max_compression_ratio:.0f}:1 (zip bomb?)"
            )
    return found


def _member_name(stored_name: str) -> str:
    """A member path normalised: ``\\`` as ``/``, empty and ``.`` components dropped."""
    return "/".join(p for p in re.split(r"[/\\]", stored_name) if p and p != ".")


def _reject_all(entries: dict[str, SubmissionFile]) -> dict[str, SubmissionFile]:
    return {n: SubmissionFile(n, e.stored_name, e.size, None) for n, e in entries.items()}


def _zip_entries(
    archive: zipfile.ZipFile, limits: SubmissionLimits, problems: list[str]
) -> dict[str, SubmissionFile]:
    infos = archive.infolist()
    if len(infos) > limits.max_members:
        problems.append(
            f"archive holds {len(infos)} members, more than the limit of {limits.max_members}"
        )
        return {}
    names = (_member_name(info.filename) for info in infos if not info.is_dir())
    counts = Counter(n for n in names if n and not _is_ignored(tuple(n.split("/"))))
    for name, count in counts.items():
        if count > 1:
            problems.append(f"{name!r}: appears {count} times in the archive")
    entries: dict[str, SubmissionFile] = {}
    total = 0
    # members are read on handles of their own (zipmember), opened by this path
    archive_path = None if archive.filename is None else Path(archive.filename).absolute()
    for info in infos:
        if info.is_dir():
            continue
        unsafe = _unsafe_path(info.filename)
        if unsafe is not None:
            problems.append(unsafe)
            continue
        name = _member_name(info.filename)
        parts = tuple(name.split("/"))
        if not name or _is_ignored(parts):
            continue
        if name in entries:
            continue  # a duplicate name, reported above
        member_problems = _zip_member_problems(info, limits)
        problems.extend(member_problems)
        total += info.file_size
        if member_problems or counts[name] > 1:
            entries[name] = SubmissionFile(name, info.filename, info.file_size, None)
            continue

        def opener(info: zipfile.ZipInfo = info) -> io.RawIOBase:
            limit = min(info.file_size, limits.max_member_bytes)
            member: io.RawIOBase | io.BufferedIOBase | None = (
                None if archive_path is None else open_member(archive_path, info)
            )
            if member is None:  # another method: zipfile's ZipExtFile
                member = cast(io.BufferedIOBase, archive.open(info))
            return _CappedReader(member, limit)

        entries[name] = SubmissionFile(name, info.filename, info.file_size, opener)
    if total > limits.max_total_bytes:
        problems.append(
            f"total uncompressed size {total} bytes exceeds the limit of "
            f"{limits.max_total_bytes} bytes"
        )
        return _reject_all(entries)
    return entries


def _is_run_record(folder: Path, filename: str) -> bool:
    """``NAME.labels.json`` beside ``NAME.labels``: the run record a baseline's ``predict``
    writes (run time, hardware). Ignored in a folder, so that predictions evaluate where
    they were written; a zip submission holds label files only, as the protocol says."""
    return filename.endswith(".labels.json") and (folder / filename[: -len(".json")]).is_file()


def _folder_entries(
    root: Path, limits: SubmissionLimits, problems: list[str]
) -> dict[str, SubmissionFile]:
    entries: dict[str, SubmissionFile] = {}
    total = 0
    for folder, dirnames, filenames in os.walk(root, followlinks=False):
        base = Path(folder)
        for dirname in sorted(dirnames):
            if (base / dirname).is_symlink():
                problems.append(
                    f"{(base / dirname).relative_to(root).as_posix()!r}: symbolic link "
                    "(expected regular files)"
                )
        for filename in sorted(filenames):
            path = base / filename
            relative = path.relative_to(root)
            if _is_ignored(relative.parts) or _is_run_record(base, filename):
                continue
            name = relative.as_posix()
            if path.is_symlink():
                problems.append(f"{name!r}: symbolic link (expected regular files)")
                entries[name] = SubmissionFile(name, name, 0, None)
                continue
            size = path.stat().st_size
            total += size
            if size > limits.max_member_bytes:
                problems.append(
                    f"{name!r}: size {size} bytes exceeds the limit of "
                    f"{limits.max_member_bytes} bytes"
                )
                entries[name] = SubmissionFile(name, name, size, None)
                continue

            def opener(path: Path = path) -> io.RawIOBase:
                return path.open("rb", buffering=0)

            entries[name] = SubmissionFile(name, name, size, opener)
    if total > limits.max_total_bytes:
        problems.append(
            f"total size {total} bytes exceeds the limit of {limits.max_total_bytes} bytes"
        )
        return _reject_all(entries)
    return entries


@contextmanager
def open_submission(
    submission: Path, *, challenge: Challenge, limits: SubmissionLimits
) -> Iterator[SubmissionContents]:
    """Open a submission (zip or folder) and check its layout against ``challenge``.

    Yields the files matched to the challenge's submission names (opened lazily) and the
    layout problems found; reading the files is left to the caller. A path that is neither
    a folder nor a readable zip archive raises :class:`SubmissionError` at once.
    """
    source = str(submission)
    problems: list[str] = []
    if submission.is_dir():
        entries = _folder_entries(submission, limits, problems)
        entries = _strip_top_folder(entries, problems)
        yield SubmissionContents(_match_names(entries, challenge, problems), problems)
        return
    if not submission.is_file():
        raise SubmissionError(["expected a zip archive or a folder, found nothing"], source=source)
    with submission.open("rb") as handle:
        magic = handle.read(4)
    if not zipfile.is_zipfile(submission):
        if magic == _ZIP_MAGIC:
            what = "a corrupt or truncated zip archive (no central directory)"
        else:
            what = f"a file that is not a zip archive (starts with {magic!r})"
        raise SubmissionError(
            [f"expected a zip archive or a folder of .labels files, found {what}"], source=source
        )
    directory_problem = check_zip_directory(
        submission,
        max_members=limits.max_members,
        max_directory_bytes=limits.max_directory_bytes,
    )
    if directory_problem is not None:
        raise SubmissionError([directory_problem], source=source)
    try:
        archive = zipfile.ZipFile(submission)
    except (zipfile.BadZipFile, OSError, ValueError, NotImplementedError) as exc:
        raise SubmissionError(
            [f"expected a readable zip archive, found a corrupt or truncated one ({exc})"],
            source=source,
        ) from None
    with archive:
        entries = _zip_entries(archive, limits, problems)
        entries = _strip_top_folder(entries, problems)
        yield SubmissionContents(_match_names(entries, challenge, problems), problems)


def read_failure(name: str, exc: BaseException) -> str:
    """The problem message for a file that could not be read to its end."""
    if isinstance(exc, _LimitExceededError):
        return f"{name}: inflates to {exc} (zip bomb?), reading stopped"
    return f"{name}: corrupt archive member, reading failed ({type(exc).__name__}: {exc})"


READ_FAILURES: tuple[type[BaseException], ...] = (_LimitExceededError, *_READ_ERRORS)
"""Exceptions that mean a submission file could not be read (reported, not raised)."""
