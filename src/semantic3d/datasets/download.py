"""Download the benchmark's scans: resumable HTTP, retries, 7z extraction, renames.

``download_split(Split.TRAIN, to=folder)`` fetches every archive a split needs, unpacks the
wanted members and lands them under their local names (``neugasse_station1_...`` included)
side by side in ``folder``. The guarantees:

- a final file name only ever holds a complete file: archives download to ``<name>.part``
  and are renamed when complete; members extract into a temporary folder on the same
  filesystem and are moved into place with ``Path.replace`` (an atomic rename);
- files already present are skipped, and an interrupted ``.part`` is continued with an HTTP
  ``Range`` request (on a later run, or on a retry after a dropped connection);
- transient failures (dropped connections, short bodies, timeouts, HTTP 408/429/5xx) are
  retried with exponential backoff, each wait reported to the progress callback; other
  HTTP errors, and a host name that does not resolve, fail at once;
- one scan failing does not stop the others: every scan is attempted, then
  :class:`IncompleteDownloadError` lists each failure with its cause.

Only the standard library (``urllib``) speaks HTTP; ``py7zr`` (extra ``download``) unpacks.
"""

from __future__ import annotations

import contextlib
import http.client
import logging
import re
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from semantic3d import __version__
from semantic3d.core.errors import DownloadError
from semantic3d.datasets.archive import extract_members
from semantic3d.datasets.registry import DEFAULT_BASE_URL, ArchiveFile, ScanInfo, Split, scans

__all__ = [
    "DOWNLOADS_DIRNAME",
    "DownloadProgress",
    "DownloadReport",
    "IncompleteDownloadError",
    "ScanDownload",
    "download_file",
    "download_scans",
    "download_split",
]

logger = logging.getLogger(__name__)

#: Sub-folder of the target folder that holds archives while they download and unpack.
DOWNLOADS_DIRNAME = ".downloads"

_CHUNK_BYTES = 1 << 20
_RETRYABLE_STATUS = frozenset({408, 425, 429, 500, 502, 503, 504})
_CONTENT_RANGE = re.compile(r"bytes\s+(\d+)-(\d+)/(\d+|\*)")


@dataclass(frozen=True, slots=True)
class DownloadProgress:
    """A progress report for one archive: ``done_bytes`` of ``total_bytes`` (``None``: unknown).

    ``done_bytes`` starts at the size of a resumed ``.part`` file, not at zero. While the
    download waits to retry, ``waiting`` says why and for how long
    (``connection failed: ...; retry 2/5 in 2 s``); it is ``None`` while bytes flow.
    """

    url: str
    filename: str
    done_bytes: int
    total_bytes: int | None
    waiting: str | None = None


ProgressCallback = Callable[[DownloadProgress], None]


@dataclass(frozen=True, slots=True)
class ScanDownload:
    """What happened to one scan: where its files are, or why it failed.

    ``error`` names the scan and the cause, e.g. ``sg27_station10_reduced: http://...: HTTP 404``.
    """

    scan: ScanInfo
    paths: tuple[Path, ...]
    skipped: bool = False
    error: DownloadError | None = None

    @property
    def ok(self) -> bool:
        """Whether every file of the scan is in place."""
        return self.error is None


@dataclass(frozen=True, slots=True)
class DownloadReport:
    """The outcome of a download, one entry per scan, in registry order."""

    folder: Path
    scans: tuple[ScanDownload, ...]

    @property
    def failures(self) -> tuple[ScanDownload, ...]:
        """The scans that did not complete."""
        return tuple(item for item in self.scans if not item.ok)

    @property
    def downloaded(self) -> tuple[ScanDownload, ...]:
        """The scans fetched by this call (not already present)."""
        return tuple(item for item in self.scans if item.ok and not item.skipped)

    @property
    def skipped(self) -> tuple[ScanDownload, ...]:
        """The scans that were already complete."""
        return tuple(item for item in self.scans if item.ok and item.skipped)


class IncompleteDownloadError(DownloadError):
    """Some scans failed; ``report`` holds every scan's outcome, ``failures`` the failed ones."""

    def __init__(self, report: DownloadReport) -> None:
        self.report = report
        self.failures = report.failures
        lines = "\n".join(f"  - {item.error}" for item in self.failures)
        total = len(report.scans)
        super().__init__(
            f"{report.folder}: {len(self.failures)} of {total} scans failed to download:\n{lines}"
        )


class _TransientError(Exception):
    """A failure worth retrying (connection dropped, short body, 5xx...)."""


def download_split(
    split: Split | str,
    *,
    to: Path,
    base_url: str | None = None,
    progress: ProgressCallback | None = None,
    retries: int = 5,
    backoff_s: float = 1.0,
    timeout_s: float = 60.0,
    keep_archives: bool = False,
) -> DownloadReport:
    """Download every scan of ``split`` into the folder ``to``; see :func:`download_scans`."""
    return download_scans(
        scans(split),
        to=to,
        base_url=base_url,
        progress=progress,
        retries=retries,
        backoff_s=backoff_s,
        timeout_s=timeout_s,
        keep_archives=keep_archives,
    )


def download_scans(
    wanted: Iterable[ScanInfo],
    *,
    to: Path,
    base_url: str | None = None,
    progress: ProgressCallback | None = None,
    retries: int = 5,
    backoff_s: float = 1.0,
    timeout_s: float = 60.0,
    keep_archives: bool = False,
) -> DownloadReport:
    """Download ``wanted`` scans into ``to`` (points and, for training scans, labels).

    Args:
        wanted: registry scans (see :func:`~semantic3d.datasets.registry.scans`).
        to: target folder; created if needed. Files land flat, under their local names.
        base_url: data root of a mirror (default :data:`DEFAULT_BASE_URL`); archive paths
            such as ``point-clouds/training1/<stem>.7z`` are appended to it.
        progress: called with a :class:`DownloadProgress` as archive bytes arrive.
        retries: extra attempts per archive after a transient failure.
        backoff_s: wait before the first retry; doubles on each further retry.
        timeout_s: socket timeout per request.
        keep_archives: keep the ``.7z`` files in ``to/.downloads`` after unpacking.

    Returns the report when every scan is complete; raises :class:`IncompleteDownloadError`
    (its ``report`` lists every scan) after trying them all when any failed.
    """
    if retries < 0:
        raise ValueError(f"retries: expected a count >= 0, found {retries}")
    folder = Path(to)
    folder.mkdir(parents=True, exist_ok=True)
    root = base_url or DEFAULT_BASE_URL
    wanted = tuple(wanted)

    # Which files are missing, grouped by the archive that holds them.
    missing: dict[str, list[ArchiveFile]] = {}
    for info in wanted:
        for item in info.files:
            if not (folder / item.filename).is_file():
                missing.setdefault(item.archive, []).append(item)

    archive_errors: dict[str, DownloadError] = {}
    for archive_path, items in missing.items():
        try:
            _fetch_and_unpack(
                items,
                folder=folder,
                url=items[0].url(root),
                progress=progress,
                retries=retries,
                backoff_s=backoff_s,
                timeout_s=timeout_s,
                keep_archive=keep_archives,
            )
        except DownloadError as exc:
            logger.info("%s", exc)
            archive_errors[archive_path] = exc

    results = []
    for info in wanted:
        needed = [item for item in info.files if item.archive in missing]
        errors = [archive_errors[item.archive] for item in needed if item.archive in archive_errors]
        paths = tuple(folder / item.filename for item in info.files)
        error = None
        if errors:
            causes = "; ".join(dict.fromkeys(str(exc) for exc in errors))
            error = DownloadError(f"{info.name}: {causes}")
        results.append(ScanDownload(info, paths, skipped=not needed, error=error))
    report = DownloadReport(folder=folder, scans=tuple(results))
    if report.failures:
        raise IncompleteDownloadError(report)
    return report


def _fetch_and_unpack(
    items: list[ArchiveFile],
    *,
    folder: Path,
    url: str,
    progress: ProgressCallback | None,
    retries: int,
    backoff_s: float,
    timeout_s: float,
    keep_archive: bool,
) -> None:
    downloads = folder / DOWNLOADS_DIRNAME
    archive = downloads / items[0].archive_name
    try:
        if not archive.is_file():
            download_file(
                url,
                archive,
                progress=progress,
                retries=retries,
                backoff_s=backoff_s,
                timeout_s=timeout_s,
            )
        try:
            extract_members(archive, {item.member: folder / item.filename for item in items})
        except DownloadError:
            # A complete but unreadable archive would fail the same way next time: drop it.
            archive.unlink(missing_ok=True)
            raise
        if not keep_archive:
            archive.unlink(missing_ok=True)
    finally:
        _remove_if_empty(downloads)


def download_file(
    url: str,
    destination: Path,
    *,
    progress: ProgressCallback | None = None,
    retries: int = 5,
    backoff_s: float = 1.0,
    timeout_s: float = 60.0,
) -> Path:
    """Download ``url`` to ``destination`` through ``<destination>.part``, resuming and retrying.

    An existing ``.part`` file is continued with a ``Range`` request; a server that ignores
    the range restarts the file. Transient failures are retried ``retries`` times with
    exponential backoff (``backoff_s``, then doubled). The ``.part`` file is renamed to
    ``destination`` only once its size matches the size the server announced.
    """
    destination.parent.mkdir(parents=True, exist_ok=True)
    part = destination.with_name(destination.name + ".part")
    failures = 0  # consecutive attempts that brought no new bytes
    while True:
        before = part.stat().st_size if part.exists() else 0
        try:
            _download_once(url, part, progress=progress, timeout_s=timeout_s)
            break
        except _TransientError as exc:
            grew = part.exists() and part.stat().st_size > before
            failures = 1 if grew else failures + 1
            if failures > retries:
                kept = f" (partial download kept in {part})" if part.exists() else ""
                raise DownloadError(
                    f"{url}: gave up after {failures} failed attempts: {exc}{kept}"
                ) from exc
            delay = backoff_s * 2 ** (failures - 1)
            waiting = f"{exc}; retry {failures}/{retries} in {delay:.0f} s"
            logger.info("%s: %s", url, waiting)
            if progress is not None:
                done = part.stat().st_size if part.exists() else 0
                progress(DownloadProgress(url, destination.name, done, None, waiting))
            time.sleep(delay)
    part.replace(destination)
    return destination


def _download_once(
    url: str, part: Path, *, progress: ProgressCallback | None, timeout_s: float
) -> None:
    offset = part.stat().st_size if part.exists() else 0
    request = urllib.request.Request(url, headers={"User-Agent": f"semantic3d/{__version__}"})
    if offset:
        request.add_header("Range", f"bytes={offset}-")
    try:
        response = urllib.request.urlopen(request, timeout=timeout_s)
    except urllib.error.HTTPError as exc:
        exc.close()
        if exc.code == 416 and offset:
            # Nothing left to send: complete if the server's size matches what we hold.
            total = _total_from_content_range(exc.headers.get("Content-Range"))
            if total == offset:
                return
            part.unlink()
            raise _TransientError("HTTP 416: partial download does not match; restarting") from exc
        if exc.code in _RETRYABLE_STATUS:
            raise _TransientError(f"HTTP {exc.code} {exc.reason}") from exc
        raise DownloadError(f"{url}: HTTP {exc.code} {exc.reason}") from exc
    except (urllib.error.URLError, OSError, http.client.HTTPException) as exc:
        if isinstance(getattr(exc, "reason", exc), socket.gaierror):
            # The name does not resolve (no network, or a wrong address): trying again
            # a few seconds later would only make the user wait for the same answer.
            host = urllib.parse.urlsplit(url).hostname
            raise DownloadError(
                f"{url}: expected the host {host} to resolve, found no address for it "
                f"({_reason(exc)}); check the network or --url"
            ) from exc
        raise _TransientError(f"connection failed: {_reason(exc)}") from exc

    with response:
        status = getattr(response, "status", 200)
        length = response.headers.get("Content-Length")
        if status == 206:
            start, total = _parse_content_range(response.headers.get("Content-Range"), url)
            if start != offset:
                part.unlink(missing_ok=True)
                raise _TransientError(f"server resumed at byte {start}, expected {offset}")
            mode = "ab"
        else:
            if offset:
                logger.info("%s: server ignored the range request; restarting", url)
            offset = 0
            total = int(length) if length is not None else None
            mode = "wb"
        done = offset
        name = part.name.removesuffix(".part")
        if progress is not None:
            progress(DownloadProgress(url, name, done, total))
        with part.open(mode) as sink:
            while True:
                try:
                    chunk = response.read(_CHUNK_BYTES)
                except (OSError, http.client.HTTPException) as exc:
                    raise _TransientError(
                        f"connection dropped at byte {done}: {_reason(exc)}"
                    ) from exc
                if not chunk:
                    break
                try:
                    sink.write(chunk)
                except OSError as exc:
                    raise DownloadError(f"{part}: cannot write: {exc}") from exc
                done += len(chunk)
                if progress is not None:
                    progress(DownloadProgress(url, name, done, total))
    if total is not None and done != total:
        raise _TransientError(f"connection dropped at byte {done} of {total}")


def _parse_content_range(value: str | None, url: str) -> tuple[int, int | None]:
    match = _CONTENT_RANGE.match(value or "")
    if match is None:
        raise _TransientError(f"malformed Content-Range {value!r} in a 206 response from {url}")
    total = None if match.group(3) == "*" else int(match.group(3))
    return int(match.group(1)), total


def _total_from_content_range(value: str | None) -> int | None:
    match = re.match(r"bytes\s+\*/(\d+)", value or "")
    return int(match.group(1)) if match else None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, urllib.error.URLError) and not isinstance(exc, urllib.error.HTTPError):
        return str(exc.reason)
    return str(exc) or type(exc).__name__


def _remove_if_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not empty, or already gone
        folder.rmdir()
