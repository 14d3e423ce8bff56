"""The member count and size of a zip's central directory, read before any index is built.

``zipfile.ZipFile`` parses the whole central directory into ``ZipInfo`` objects when it
opens an archive: a million empty entries (90 MB) cost ~12 s of CPU and ~500 MB before
any member cap can answer. These checks read the end-of-central-directory record (and
the ZIP64 one), then walk at most ``max_members + 1`` directory entries' fixed headers.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

# End-of-central-directory records (APPNOTE 4.3.16, 4.3.15, 4.3.14) and a directory entry.
_EOCD = struct.Struct("<4s4H2LH")
_EOCD_SIGNATURE = b"PK\x05\x06"
_EOCD64_LOCATOR = struct.Struct("<4sLQL")
_EOCD64_LOCATOR_SIGNATURE = b"PK\x06\x07"
_EOCD64 = struct.Struct("<4sQ2H2L4Q")
_EOCD64_SIGNATURE = b"PK\x06\x06"
_CENTRAL_ENTRY_SIZE = 46
_CENTRAL_NAME_LENGTHS = struct.Struct("<3H")  # name, extra field, comment; at byte 28
_CENTRAL_SIGNATURE = b"PK\x01\x02"
_MAX_COMMENT = 0xFFFF


def check_zip_directory(path: Path, *, max_members: int, max_directory_bytes: int) -> str | None:
    """The problem with a zip's central directory, read cheaply before any index is built.

    Reads the end-of-central-directory record (and the ZIP64 one when present): a
    declared member count over ``max_members`` or a directory larger than
    ``max_directory_bytes`` is refused from those few bytes. The directory is then
    walked entry by entry (at most ``max_members + 1`` of them, header fields only), so a
    record that understates the count is caught as cheaply. Anything malformed is left
    to :mod:`zipfile` to report (``None``).
    """
    with path.open("rb") as handle:
        size = handle.seek(0, os.SEEK_END)
        tail_size = min(size, _EOCD.size + _MAX_COMMENT)
        handle.seek(size - tail_size)
        tail = handle.read(tail_size)
        at = tail.rfind(_EOCD_SIGNATURE)
        if at < 0 or len(tail) - at < _EOCD.size:
            return None
        record = _EOCD.unpack_from(tail, at)
        eocd_offset = size - tail_size + at
        n_entries, directory_size = record[4], record[5]
        directory_end = eocd_offset
        locator_offset = eocd_offset - _EOCD64_LOCATOR.size
        if locator_offset - _EOCD64.size >= 0:
            handle.seek(locator_offset)
            locator = handle.read(_EOCD64_LOCATOR.size)
            if locator[:4] == _EOCD64_LOCATOR_SIGNATURE:
                handle.seek(locator_offset - _EOCD64.size)
                record64 = handle.read(_EOCD64.size)
                if record64[:4] == _EOCD64_SIGNATURE:
                    fields = _EOCD64.unpack(record64)
                    n_entries, directory_size = fields[7], fields[8]
                    directory_end = locator_offset - _EOCD64.size
        if n_entries > max_members:
            return _too_many_members(f"{n_entries}", max_members)
        if directory_size > max_directory_bytes:
            return (
                f"central directory of {directory_size} bytes, more than the limit of "
                f"{max_directory_bytes} bytes (too many members or overlong names)"
            )
        start = directory_end - directory_size
        if start < 0:
            return None  # inconsistent record: zipfile reports the corruption
        handle.seek(start)
        directory = handle.read(directory_size)
    return _walk_directory(directory, max_members)


def _walk_directory(directory: bytes, max_members: int) -> str | None:
    position = count = 0
    end = len(directory) - _CENTRAL_ENTRY_SIZE
    while position <= end:
        if directory[position : position + 4] != _CENTRAL_SIGNATURE:
            return None
        count += 1
        if count > max_members:
            return _too_many_members(f"more than {max_members}", max_members)
        name, extra, comment = _CENTRAL_NAME_LENGTHS.unpack_from(directory, position + 28)
        position += _CENTRAL_ENTRY_SIZE + name + extra + comment
    return None


def _too_many_members(count: str, max_members: int) -> str:
    return f"archive holds {count} members, more than the limit of {max_members}"
