"""A zip's central directory, found and walked exactly as :mod:`zipfile` will, before its index.

``zipfile.ZipFile`` parses the whole central directory into ``ZipInfo`` objects when it
opens an archive: a million empty entries (90 MB) cost ~12 s of CPU and ~500 MB before
any member cap can answer. :func:`check_zip_directory` reads what ``zipfile`` reads, in
the order it reads it (``zipfile._EndRecData`` and ``_RealGetContents``):

1. the end-of-central-directory record: the last 22 bytes when they hold one without a
   comment, else the last record signature in the final 64 KiB + 22 bytes;
2. the ZIP64 locator right before that record and, when there is one, the ZIP64 end
   record right before the locator;
3. the directory, which ``zipfile`` reads from ``record start - directory size``,
   entry header by entry header until the declared size is used up.

An archive passes only when every way of reading it agrees: the record and its comment
end the file; the ZIP64 locator points at the ZIP64 record (newer ``zipfile`` versions and
other tools follow the pointer, older ones assume the record sits before the locator)
and that record has no extensible data; one disk; the directory starts at the offset the
record declares (no bytes before the archive); the walk ends exactly at the declared
size; and the declared entry count is the number of entries walked. That count is then
the number ``zipfile`` will index, and it is checked against ``max_members`` from the
record alone before anything else is read (a forged offset field, such as the bytes of a
record signature placed in it, changes nothing: the record is found where ``zipfile``
finds it). The walk reads fixed headers only, in 1 MiB blocks, and stops after
``max_members + 1`` entries, so a record that understates the count costs as little.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import BinaryIO

# End-of-central-directory record, ZIP64 locator and ZIP64 end record (APPNOTE 4.3.16,
# 4.3.15, 4.3.14); a central directory entry's fixed header (4.3.12).
_EOCD = struct.Struct("<4s4H2LH")
_EOCD_SIGNATURE = b"PK\x05\x06"
_LOCATOR = struct.Struct("<4sLQL")
_LOCATOR_SIGNATURE = b"PK\x06\x07"
_EOCD64 = struct.Struct("<4sQ2H2L4Q")
_EOCD64_SIGNATURE = b"PK\x06\x06"
_EOCD64_FIXED_SIZE = _EOCD64.size - 12  # the record's own size field counts from byte 12
_ENTRY_SIZE = 46
_ENTRY_SIGNATURE = b"PK\x01\x02"
_ENTRY_VERSION = struct.Struct("<H")  # version needed to extract; at byte 6
_ENTRY_LENGTHS = struct.Struct("<3H")  # name, extra field, comment; at byte 28
_MAX_COMMENT = 0xFFFF
_MAX_EXTRACT_VERSION = 63  # zipfile.MAX_EXTRACT_VERSION: higher raises NotImplementedError
_BLOCK = 1 << 20


class _RefusedError(Exception):
    """The directory cannot be read cleanly; the message says why."""


def check_zip_directory(path: Path, *, max_members: int, max_directory_bytes: int) -> str | None:
    """The problem with a zip's central directory (``None``: ``zipfile`` may index it).

    See the module docstring: the directory is located and walked as ``zipfile`` will,
    and refused unless every reading of it agrees, the declared member count is at most
    ``max_members`` and is the count walked, and the directory takes at most
    ``max_directory_bytes``. Reads the record, the ZIP64 records and the entries' fixed
    headers; memory stays under 2 MiB whatever the archive.
    """
    with path.open("rb") as handle:
        try:
            _check(handle, max_members=max_members, max_directory_bytes=max_directory_bytes)
        except _RefusedError as exc:
            return str(exc)
    return None


def _check(handle: BinaryIO, *, max_members: int, max_directory_bytes: int) -> None:
    size = handle.seek(0, os.SEEK_END)
    record, record_at = _end_record(handle, size)
    disk, directory_disk, n_here, n_entries, directory_size, directory_offset = record[:6]
    directory_end = record_at
    zip64 = _zip64_record(handle, record_at)
    if zip64 is not None:
        directory_end, fields = zip64
        disk, directory_disk, n_here, n_entries, directory_size, directory_offset = fields
    if disk != 0 or directory_disk != 0 or n_here != n_entries:
        raise _RefusedError(_corrupt("a multi-disk archive"))
    if n_entries > max_members:
        raise _RefusedError(_too_many_members(str(n_entries), max_members))
    if directory_size > max_directory_bytes:
        raise _RefusedError(
            f"central directory of {directory_size} bytes, more than the limit of "
            f"{max_directory_bytes} bytes (too many members or overlong names)"
        )
    start = directory_end - directory_size  # where zipfile starts reading the directory
    if start < 0:
        raise _RefusedError(
            _corrupt(
                f"a central directory of {directory_size} bytes that does not fit before "
                f"its end record at byte {directory_end}"
            )
        )
    if start != directory_offset:
        raise _RefusedError(
            _corrupt(
                f"the central directory at byte {start} where its end record says byte "
                f"{directory_offset} (bytes before the archive, or a forged record)"
            )
        )
    walked = _walk_directory(handle, start, directory_size, max_members)
    if walked != n_entries:
        raise _RefusedError(
            _corrupt(
                f"an end record declaring {n_entries} members over a central directory of {walked}"
            )
        )


def _end_record(handle: BinaryIO, size: int) -> tuple[tuple[int, ...], int]:
    """The end record's fields (after its signature) as ``zipfile._EndRecData`` finds it,
    and where it starts."""
    if size >= _EOCD.size:
        handle.seek(size - _EOCD.size)
        data = handle.read(_EOCD.size)
        if data[:4] == _EOCD_SIGNATURE and data[-2:] == b"\x00\x00":
            return _EOCD.unpack(data)[1:], size - _EOCD.size
    search_from = max(size - _MAX_COMMENT - 1 - _EOCD.size, 0)
    handle.seek(search_from)
    data = handle.read()
    at = data.rfind(_EOCD_SIGNATURE)
    if at < 0 or len(data) - at < _EOCD.size:
        raise _RefusedError(_corrupt("no end-of-central-directory record"))
    record = _EOCD.unpack_from(data, at)[1:]
    comment_size = record[6]
    after = len(data) - at - _EOCD.size
    if comment_size != after:
        raise _RefusedError(
            _corrupt(
                f"an end record at byte {search_from + at} declaring a {comment_size}-byte "
                f"comment followed by {after} bytes"
            )
        )
    return record, search_from + at


def _zip64_record(handle: BinaryIO, record_at: int) -> tuple[int, tuple[int, ...]] | None:
    """Where the ZIP64 end record starts and its fields, when a ZIP64 locator is present.

    ``zipfile`` looks for the locator right before the end record and, before 3.14 (and
    its security releases), for the ZIP64 record right before the locator; later ones
    follow the locator's pointer. Both must find the same record.
    """
    locator_at = record_at - _LOCATOR.size
    if locator_at < 0:
        return None
    handle.seek(locator_at)
    data = handle.read(_LOCATOR.size)
    if data[:4] != _LOCATOR_SIGNATURE:
        return None
    _, record_disk, pointer, n_disks = _LOCATOR.unpack(data)
    if record_disk != 0 or n_disks > 1:
        raise _RefusedError(_corrupt("a multi-disk archive"))
    zip64_at = locator_at - _EOCD64.size
    if zip64_at < 0:
        raise _RefusedError(_corrupt("a ZIP64 locator with no room for its ZIP64 end record"))
    handle.seek(zip64_at)
    record = handle.read(_EOCD64.size)
    if record[:4] != _EOCD64_SIGNATURE:
        raise _RefusedError(_corrupt("a ZIP64 locator without its ZIP64 end record"))
    if pointer != zip64_at:
        raise _RefusedError(
            _corrupt(
                f"a ZIP64 locator pointing at byte {pointer}, the ZIP64 end record at byte "
                f"{zip64_at}"
            )
        )
    fields = _EOCD64.unpack(record)
    if fields[1] != _EOCD64_FIXED_SIZE:
        raise _RefusedError(
            _corrupt(
                f"a ZIP64 end record of {fields[1] + 12} bytes (extensible data; "
                f"expected {_EOCD64.size} bytes)"
            )
        )
    disk, directory_disk, n_here, n_entries, directory_size, directory_offset = fields[4:]
    return zip64_at, (disk, directory_disk, n_here, n_entries, directory_size, directory_offset)


def _walk_directory(handle: BinaryIO, start: int, size: int, max_members: int) -> int:
    """Count the entries ``zipfile`` will index (at most ``max_members + 1`` are walked)."""
    window = b""
    window_at = 0  # directory offset of window[0]
    position = count = 0
    while position < size:
        if position + _ENTRY_SIZE > window_at + len(window):
            handle.seek(start + position)
            window = handle.read(min(_BLOCK, size - position))
            window_at = position
        header = window[position - window_at : position - window_at + _ENTRY_SIZE]
        if len(header) < _ENTRY_SIZE:
            raise _RefusedError(
                _corrupt(f"a central directory ending inside an entry at byte {start + position}")
            )
        if header[:4] != _ENTRY_SIGNATURE:
            raise _RefusedError(_corrupt(f"no central directory entry at byte {start + position}"))
        count += 1
        if count > max_members:
            raise _RefusedError(_too_many_members(f"more than {max_members}", max_members))
        (version,) = _ENTRY_VERSION.unpack_from(header, 6)
        if version > _MAX_EXTRACT_VERSION:
            raise _RefusedError(
                f"member {count} needs zip version {version / 10:.1f} to extract "
                f"(expected at most {_MAX_EXTRACT_VERSION / 10:.1f})"
            )
        name, extra, comment = _ENTRY_LENGTHS.unpack_from(header, 28)
        position += _ENTRY_SIZE + name + extra + comment
    if position != size:
        raise _RefusedError(
            _corrupt(
                f"a last central directory entry running {position - size} bytes past "
                "the directory's declared end"
            )
        )
    return count


def _corrupt(what: str) -> str:
    return f"expected a consistent zip archive, found {what}"


def _too_many_members(count: str, max_members: int) -> str:
    return f"archive holds {count} members, more than the limit of {max_members}"
