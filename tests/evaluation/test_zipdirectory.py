"""check_zip_directory: the central directory read as zipfile reads it, or refused.

Every archive it accepts, zipfile indexes with exactly the declared member count; every
archive two readers could read differently is refused, each with its own message.
"""

from __future__ import annotations

import io
import struct
import tempfile
import zipfile
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.evaluation.zipdirectory import check_zip_directory
from tests.budgets import Budget

EOCD = struct.Struct("<4s4H2LH")
LOCATOR = struct.Struct("<4sLQL")
EOCD64 = struct.Struct("<4sQ2H2L4Q")
BAD = "expected a consistent zip archive, found "


def check(data: bytes, tmp_path: Path, *, max_members: int = 10_000) -> str | None:
    path = tmp_path / "archive.zip"
    path.write_bytes(data)
    return check_zip_directory(path, max_members=max_members, max_directory_bytes=16 << 20)


def zip_of(n_members: int, *, comment: bytes = b"") -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for i in range(n_members):
            archive.writestr(f"{i}.labels", b"1\n" * (i + 1))
        archive.comment = comment
    return buffer.getvalue()


def raw_zip(n_entries: int, *, zip64: bool = False) -> bytes:
    """``n_entries`` empty stored members written directly (fast), optionally with ZIP64 end
    records (the classic record then holds 0xFFFF / 0xFFFFFFFF)."""
    local, central, offset = [], [], 0
    for i in range(n_entries):
        name = b"%07d" % i
        local += [struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, 0, 0, 0, 0, 0, 0, 7, 0), name]
        central += [
            struct.pack(
                "<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, 0, 0, 0, 0, 0, 0, 7, 0, 0, 0, 0, 0, offset
            ),
            name,
        ]
        offset += 37
    directory = b"".join(central)
    if not zip64:
        end = EOCD.pack(b"PK\x05\x06", 0, 0, n_entries, n_entries, len(directory), offset, 0)
        return b"".join(local) + directory + end
    at = offset + len(directory)
    records = EOCD64.pack(
        b"PK\x06\x06", 44, 45, 45, 0, 0, n_entries, n_entries, len(directory), offset
    ) + LOCATOR.pack(b"PK\x06\x07", 0, at, 1)
    end = EOCD.pack(b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    return b"".join(local) + directory + records + end


def with_end(data: bytes, **fields: int) -> bytes:
    """``data`` with fields of its (comment-less) classic end record replaced."""
    names = ["disk", "directory_disk", "here", "total", "size", "offset", "comment"]
    values = dict(zip(names, EOCD.unpack(data[-22:])[1:], strict=True))
    values.update(fields)
    return data[:-22] + EOCD.pack(b"PK\x05\x06", *values.values())


def indexed(data: bytes) -> int:
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return len(archive.infolist())


# What is accepted: exactly what zipfile indexes -------------------------------------------


def test_ordinary_archives_pass(tmp_path: Path) -> None:
    for data in (zip_of(0), zip_of(3), zip_of(3, comment=b"made by hand"), raw_zip(5, zip64=True)):
        assert check(data, tmp_path) is None
    assert indexed(raw_zip(5, zip64=True)) == 5


@settings(max_examples=80, deadline=None)
@given(
    n_members=st.integers(0, 4),
    comment=st.binary(max_size=40) | st.sampled_from([b"PK\x05\x06", b"xPK\x05\x06" + b"\0" * 18]),
    cut=st.integers(0, 30),
    noise=st.binary(min_size=1, max_size=4),
)
def test_an_accepted_archive_is_indexed_with_its_declared_count(
    n_members: int, comment: bytes, cut: int, noise: bytes
) -> None:
    # Archives with comments (some holding a record signature) and a few bytes of their
    # tail overwritten: whatever is accepted, zipfile indexes every member, no more.
    data = bytearray(zip_of(n_members, comment=comment))
    at = max(len(data) - cut, 0)
    data[at : at + len(noise)] = noise
    with tempfile.TemporaryDirectory() as folder:
        problem = check(bytes(data), Path(folder), max_members=100)
    if problem is None:
        assert indexed(bytes(data)) == n_members


# The 4-byte trick and forged counts: refused from the record, cheaply ----------------------


def test_a_record_signature_in_the_offset_field_changes_nothing(tmp_path: Path) -> None:
    # The offset field of the classic record set to the bytes "PK\x05\x06": a search for
    # the last signature finds a fake record there and used to skip every check, while
    # zipfile (last 22 bytes first) indexes all 30,000 entries (1 M: +6 s, +500 MB).
    data = bytearray(raw_zip(30_000, zip64=True))
    data[-6:-2] = b"PK\x05\x06"
    path = tmp_path / "trick.zip"
    path.write_bytes(bytes(data))
    with Budget() as budget:
        problem = check_zip_directory(path, max_members=10_000, max_directory_bytes=16 << 20)
    assert problem == "archive holds 30000 members, more than the limit of 10000"
    assert budget.cpu_s < 0.02 and budget.peak_mb < 0.5, str(budget)
    assert indexed(bytes(data)) == 30_000  # what zipfile would have built


def test_an_understated_count_is_walked_and_refused(tmp_path: Path) -> None:
    data = raw_zip(12, zip64=False)
    assert check(with_end(data, here=3, total=3), tmp_path) == (
        BAD + "an end record declaring 3 members over a central directory of 12"
    )
    assert check(with_end(data, here=3, total=3), tmp_path, max_members=10) == (
        "archive holds more than 10 members, more than the limit of 10"
    )


# Every ambiguity is refused ------------------------------------------------------------------


def test_a_forged_directory_offset(tmp_path: Path) -> None:
    data = zip_of(2)
    offset = EOCD.unpack(data[-22:])[6]
    assert check(with_end(data, offset=offset + 1), tmp_path) == (
        BAD + f"the central directory at byte {offset} where its end record says byte "
        f"{offset + 1} (bytes before the archive, or a forged record)"
    )


def test_bytes_before_the_archive(tmp_path: Path) -> None:
    data = zip_of(2)
    offset = EOCD.unpack(data[-22:])[6]
    problem = check(b"#!/bin/sh\n" + data, tmp_path)
    assert problem == (
        BAD + f"the central directory at byte {offset + 10} where its end record says byte "
        f"{offset} (bytes before the archive, or a forged record)"
    )
    assert indexed(b"#!/bin/sh\n" + data) == 2  # zipfile copes; the check does not guess


def test_a_directory_larger_than_the_file(tmp_path: Path) -> None:
    data = zip_of(2)
    end = len(data) - 22
    assert check(with_end(data, size=end + 1), tmp_path) == (
        BAD + f"a central directory of {end + 1} bytes that does not fit before its end "
        f"record at byte {end}"
    )


def test_a_comment_length_that_does_not_match(tmp_path: Path) -> None:
    data = zip_of(2, comment=b"hello")
    data = data[:-7] + struct.pack("<H", 9) + b"hello"
    assert check(data, tmp_path) == (
        BAD + f"an end record at byte {len(data) - 27} declaring a 9-byte comment followed "
        "by 5 bytes"
    )


def test_no_record(tmp_path: Path) -> None:
    assert check(b"PK\x03\x04" + b"\0" * 100, tmp_path) == (
        BAD + "no end-of-central-directory record"
    )


def test_several_disks(tmp_path: Path) -> None:
    assert check(with_end(zip_of(2), disk=1), tmp_path) == BAD + "a multi-disk archive"
    assert check(with_end(zip_of(2), here=1), tmp_path) == BAD + "a multi-disk archive"


def test_a_zip64_locator_pointing_elsewhere(tmp_path: Path) -> None:
    data = bytearray(raw_zip(3, zip64=True))
    locator = len(data) - 22 - LOCATOR.size
    record = locator - EOCD64.size
    data[locator + 8 : locator + 16] = struct.pack("<Q", 0)
    assert check(bytes(data), tmp_path) == (
        BAD + f"a ZIP64 locator pointing at byte 0, the ZIP64 end record at byte {record}"
    )


def test_a_zip64_locator_without_its_record(tmp_path: Path) -> None:
    data = bytearray(raw_zip(3, zip64=True))
    record = len(data) - 22 - LOCATOR.size - EOCD64.size
    data[record : record + 4] = b"XXXX"
    assert check(bytes(data), tmp_path) == BAD + "a ZIP64 locator without its ZIP64 end record"


def test_a_zip64_record_with_extensible_data(tmp_path: Path) -> None:
    data = bytearray(raw_zip(3, zip64=True))
    record = len(data) - 22 - LOCATOR.size - EOCD64.size
    data[record + 4 : record + 12] = struct.pack("<Q", 60)
    assert check(bytes(data), tmp_path) == (
        BAD + "a ZIP64 end record of 72 bytes (extensible data; expected 56 bytes)"
    )


def test_a_last_entry_running_past_the_directory(tmp_path: Path) -> None:
    data = bytearray(raw_zip(3))
    offset = EOCD.unpack(bytes(data[-22:]))[6]
    data[offset + 2 * 53 + 28 : offset + 2 * 53 + 30] = struct.pack("<H", 11)  # name: 7 -> 11
    assert check(bytes(data), tmp_path) == (
        BAD + "a last central directory entry running 4 bytes past the directory's declared end"
    )


def test_garbage_instead_of_an_entry(tmp_path: Path) -> None:
    data = bytearray(raw_zip(3))
    offset = EOCD.unpack(bytes(data[-22:]))[6]
    data[offset + 53 : offset + 57] = b"XXXX"  # the second entry's signature
    assert check(bytes(data), tmp_path) == BAD + f"no central directory entry at byte {offset + 53}"


def test_an_entry_needing_a_newer_zip_version(tmp_path: Path) -> None:
    data = bytearray(raw_zip(2))
    offset = EOCD.unpack(bytes(data[-22:]))[6]
    data[offset + 6 : offset + 8] = struct.pack("<H", 64)
    assert check(bytes(data), tmp_path) == (
        "member 1 needs zip version 6.4 to extract (expected at most 6.3)"
    )
