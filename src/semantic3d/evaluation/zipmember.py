"""A zip member read as :mod:`zipfile` reads it, inflated by zlib-ng, on a handle of its own.

Inflating is what bounds scoring a zipped submission: label files are long runs of one
class (they deflate 100:1 to 700:1), and the standard library's zlib inflates such runs at
0.3-0.7 GB/s here where zlib-ng (the ``zlib-ng`` package, the same API) does 5-8 GB/s.
``zipfile`` offers no choice of inflater, so stored and deflated members are read here:

- the member's local header is checked as ``zipfile.ZipFile.open`` checks it (its
  signature, the name it repeats); encrypted members and patched data are left to
  ``zipfile``;
- its compressed bytes are read with positioned reads on a file handle of the member's
  own, so scans of one archive are inflated on several threads at once (``zipfile``'s
  members share one handle and take turns on its lock);
- the bytes given are checked at the end against the directory's size and CRC-32, with
  the errors ``zipfile`` raises (:class:`zipfile.BadZipFile`, :class:`EOFError`).

Other compression methods go to ``zipfile``. Where zlib-ng is not installed, the standard
library's zlib inflates (the same bytes, slower).
"""

from __future__ import annotations

import importlib
import io
import os
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

__all__ = ["INFLATE_ERRORS", "open_member"]


def _load_inflater() -> Any:
    """zlib-ng's zlib module (the same interface as zlib's), else zlib itself."""
    try:
        return importlib.import_module("zlib_ng.zlib_ng")
    except ImportError:  # pragma: no cover - a platform without its wheels
        return zlib


_inflater: Any = _load_inflater()

INFLATE_ERRORS: tuple[type[Exception], ...] = tuple({_inflater.error, zlib.error})
"""What a corrupt deflate stream raises here (zlib-ng's error is not zlib's)."""

_LOCAL_HEADER = struct.Struct("<4s2B4HL2L2H")  # APPNOTE 4.3.7, as zipfile reads it
_LOCAL_SIGNATURE = b"PK\x03\x04"
_FLAG_UTF8 = 0x800
_FLAGS_LEFT_TO_ZIPFILE = 0x1 | 0x20 | 0x40  # encryption, compressed patched data, strong encryption
_TRUNCATED = "Compressed file ended before the end-of-stream marker was reached"  # zipfile's
_READ_BYTES = 1 << 16
"""Compressed bytes read at a time: a label file's 1 MiB of text inflates from a few KiB,
and what a read leaves over is copied again on the next."""


def open_member(archive: Path, info: zipfile.ZipInfo) -> io.RawIOBase | None:
    """A stream of ``info``'s uncompressed bytes, or None for a member ``zipfile`` must read
    (another compression method, flags it refuses)."""
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        return None
    if info.flag_bits & _FLAGS_LEFT_TO_ZIPFILE:
        return None
    fd = os.open(archive, os.O_RDONLY | getattr(os, "O_BINARY", 0))
    try:
        start = _data_start(fd, info)
    except BaseException:
        os.close(fd)
        raise
    return _MemberReader(fd, info, start)


def _data_start(fd: int, info: zipfile.ZipInfo) -> int:
    """Where the member's compressed bytes start, its local header checked."""
    header = os.pread(fd, _LOCAL_HEADER.size, info.header_offset)
    if len(header) != _LOCAL_HEADER.size:
        raise zipfile.BadZipFile("Truncated file header")
    fields = _LOCAL_HEADER.unpack(header)
    if fields[0] != _LOCAL_SIGNATURE:
        raise zipfile.BadZipFile("Bad magic number for file header")
    name_length, extra_length = fields[10], fields[11]
    name_at = info.header_offset + _LOCAL_HEADER.size
    stored = os.pread(fd, name_length, name_at)
    encoding = "utf-8" if fields[3] & _FLAG_UTF8 else "cp437"
    if stored.decode(encoding, errors="replace") != info.orig_filename:
        raise zipfile.BadZipFile(
            f"File name in directory {info.orig_filename!r} and header {stored!r} differ."
        )
    return name_at + name_length + extra_length


class _MemberReader(io.RawIOBase):
    """The uncompressed bytes of one member, checked against its size and CRC-32 at the end."""

    def __init__(self, fd: int, info: zipfile.ZipInfo, start: int) -> None:
        super().__init__()
        self._fd = fd
        self._name = info.filename
        self._at = start
        self._compressed_left = info.compress_size
        self._expected_size = info.file_size
        self._expected_crc = info.CRC
        self._given = 0
        self._crc = 0
        self._pending = b""  # compressed bytes read, not yet given to the inflater
        self._inflater: Any = (
            _inflater.decompressobj(-15) if info.compress_type == zipfile.ZIP_DEFLATED else None
        )
        self._ended = False

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        """Fill ``buffer`` (short only at the member's end, which is checked then)."""
        view = memoryview(buffer).cast("B")
        filled = 0
        while filled < len(view) and not self._ended:
            data = self._next(len(view) - filled)
            if data:
                view[filled : filled + len(data)] = data
                filled += len(data)
                self._given += len(data)
                self._crc = _inflater.crc32(data, self._crc)
            elif self._finished():
                self._check_end()
        if self._given > self._expected_size:
            raise zipfile.BadZipFile(f"{self._name}: more bytes than the directory says")
        return filled

    def _read_compressed(self, n: int) -> bytes:
        n = min(n, self._compressed_left)
        if n <= 0:
            return b""
        got = os.pread(self._fd, n, self._at)
        if not got:
            raise EOFError(_TRUNCATED)
        self._at += len(got)
        self._compressed_left -= len(got)
        return got

    def _next(self, size: int) -> bytes:
        """Up to ``size`` uncompressed bytes (none when more compressed bytes are needed)."""
        if self._inflater is None:  # stored
            return self._read_compressed(size)
        if not self._pending:  # none left at the end: an empty input drains what it holds
            self._pending = self._read_compressed(_READ_BYTES)
        data = self._inflater.decompress(self._pending, size)
        self._pending = self._inflater.unconsumed_tail
        if self._inflater.eof:
            self._pending = b""
            self._compressed_left = 0
        return data

    def _finished(self) -> bool:
        if self._inflater is None:
            return self._compressed_left <= 0
        if self._inflater.eof:
            return True
        if self._compressed_left <= 0 and not self._pending:
            raise EOFError(_TRUNCATED)
        return False

    def _check_end(self) -> None:
        self._ended = True
        if self._given != self._expected_size:
            raise zipfile.BadZipFile(
                f"{self._name}: {self._given} bytes, the directory says {self._expected_size}"
            )
        if self._crc != self._expected_crc:
            raise zipfile.BadZipFile(f"Bad CRC-32 for file {self._name!r}")

    def close(self) -> None:
        if not self.closed:
            os.close(self._fd)
        super().close()
