"""Zip members read by zlib-ng on their own handles: zipfile's bytes and zipfile's errors."""

from __future__ import annotations

import io
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from semantic3d.evaluation import zipmember
from semantic3d.evaluation.contents import READ_FAILURES
from semantic3d.evaluation.zipmember import open_member


def _read_all(stream: io.RawIOBase, size: int) -> bytes:
    out = bytearray()
    buffer = bytearray(size)
    while True:
        got = stream.readinto(buffer)
        if not got:
            return bytes(out)
        out += buffer[:got]


def _labels(runs: list[tuple[int, int]]) -> bytes:
    return b"".join(f"{value}\n".encode() * length for value, length in runs)


members = st.lists(
    st.one_of(
        st.lists(st.tuples(st.integers(0, 8), st.integers(1, 5000)), max_size=30).map(_labels),
        st.binary(max_size=3000),
    ),
    min_size=1,
    max_size=4,
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    contents=members,
    method=st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]),
    level=st.integers(0, 9),
    read_size=st.integers(1, 70_000),
)
def test_members_read_as_zipfile_reads_them(
    tmp_path: Path, contents: list[bytes], method: int, level: int, read_size: int
) -> None:
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w", compression=method, compresslevel=level) as archive:
        for number, data in enumerate(contents):
            archive.writestr(f"folder/scan{number}.labels", data)
    with zipfile.ZipFile(path) as archive:
        for info, data in zip(archive.infolist(), contents, strict=True):
            stream = open_member(path, info)
            assert stream is not None
            with stream:
                assert _read_all(stream, read_size) == data == archive.read(info)


class _Unseekable(io.RawIOBase):
    """A write-only stream zipfile cannot seek back in: it writes data descriptors."""

    def __init__(self, target: io.BufferedWriter) -> None:
        super().__init__()
        self.target = target

    def writable(self) -> bool:
        return True

    def write(self, data: bytes) -> int:  # type: ignore[override]
        return self.target.write(data)


def test_zip64_headers_and_data_descriptors_read_as_zipfile_reads_them(tmp_path: Path) -> None:
    data = _labels([(4, 30_000), (7, 9)])
    path = tmp_path / "s.zip"
    with (
        zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive,
        archive.open("zip64.labels", "w", force_zip64=True) as member,
    ):
        member.write(data)
    streamed = tmp_path / "streamed.zip"
    with (
        streamed.open("wb") as target,
        zipfile.ZipFile(_Unseekable(target), "w", compression=zipfile.ZIP_DEFLATED) as archive,
    ):
        archive.writestr("described.labels", data)
    for archive_path in (path, streamed):
        with zipfile.ZipFile(archive_path) as archive:
            (info,) = archive.infolist()
            assert archive.read(info) == data
        stream = open_member(archive_path, info)
        assert stream is not None
        with stream:
            assert _read_all(stream, 5000) == data
    assert info.flag_bits & 0x8  # the streamed member has a data descriptor


def test_the_standard_zlib_gives_the_same_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    data = _labels([(3, 200_000), (5, 7), (1, 90_000)])
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("a.labels", data)
        (info,) = archive.infolist()
    monkeypatch.setattr(zipmember, "_inflater", zlib)
    stream = open_member(path, info)
    assert stream is not None
    with stream:
        assert _read_all(stream, 1 << 20) == data


def test_members_of_one_archive_read_on_threads_at_once(tmp_path: Path) -> None:
    contents = [_labels([(n % 9, 300_000 + 1000 * n)]) for n in range(6)]
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for number, data in enumerate(contents):
            archive.writestr(f"scan{number}.labels", data)
        infos = archive.infolist()

    def read(info: zipfile.ZipInfo) -> bytes:
        stream = open_member(path, info)
        assert stream is not None
        with stream:
            return _read_all(stream, 1 << 16)

    with ThreadPoolExecutor(4) as pool:
        assert list(pool.map(read, infos)) == contents


def _deflated(tmp_path: Path, data: bytes) -> tuple[Path, zipfile.ZipInfo, int]:
    """An archive of one deflated member, its info and where its compressed bytes start."""
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("a.labels", data)
        (info,) = archive.infolist()
    return path, info, info.header_offset + 30 + len(b"a.labels")


def _fails(path: Path, info: zipfile.ZipInfo) -> BaseException:
    with pytest.raises(READ_FAILURES) as raised:
        stream = open_member(path, info)
        assert stream is not None
        with stream:
            _read_all(stream, 4096)
    return raised.value


def test_a_corrupt_deflate_stream_fails_as_zipfile_does(tmp_path: Path) -> None:
    data = bytes(range(256)) * 200
    path, info, start = _deflated(tmp_path, data)
    raw = bytearray(path.read_bytes())
    raw[start + 40 : start + 60] = b"\xff" * 20
    path.write_bytes(bytes(raw))
    with zipfile.ZipFile(path) as archive, pytest.raises(READ_FAILURES):
        archive.read("a.labels")  # what zipfile says of it: a read failure too
    _fails(path, info)


def test_a_wrong_crc_and_a_wrong_size_fail(tmp_path: Path) -> None:
    data = _labels([(2, 5000)])
    path, info, _ = _deflated(tmp_path, data)
    info.CRC ^= 1
    assert str(_fails(path, info)) == "Bad CRC-32 for file 'a.labels'"
    info.CRC ^= 1
    info.file_size -= 1
    assert isinstance(_fails(path, info), zipfile.BadZipFile)


def test_a_truncated_member_fails(tmp_path: Path) -> None:
    data = bytes(range(256)) * 400  # hardly compressible: many compressed bytes
    path, info, start = _deflated(tmp_path, data)
    with path.open("r+b") as stream:
        stream.truncate(start + info.compress_size // 2)
    assert isinstance(_fails(path, info), EOFError)


def test_a_local_header_that_disagrees_with_the_directory_fails(tmp_path: Path) -> None:
    path, info, _ = _deflated(tmp_path, b"1\n" * 100)
    raw = bytearray(path.read_bytes())
    raw[info.header_offset + 30 : info.header_offset + 31] = b"b"  # "b.labels" in the header
    path.write_bytes(bytes(raw))
    with pytest.raises(zipfile.BadZipFile, match=r"and header b'b\.labels' differ"):
        open_member(path, info)
    raw[info.header_offset : info.header_offset + 4] = b"PK\x05\x05"
    path.write_bytes(bytes(raw))
    with pytest.raises(zipfile.BadZipFile, match="Bad magic number"):
        open_member(path, info)


def test_other_methods_are_left_to_zipfile_and_handles_are_closed(tmp_path: Path) -> None:
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_BZIP2) as archive:
        archive.writestr("a.labels", b"1\n")
        (bzip2,) = archive.infolist()
    assert open_member(path, bzip2) is None
    encrypted = zipfile.ZipInfo("a.labels")
    encrypted.flag_bits |= 0x1
    assert open_member(path, encrypted) is None  # zipfile asks for its password
    path, info, _ = _deflated(tmp_path, b"1\n" * 100)
    before = len(list(Path("/proc/self/fd").iterdir()))
    for _ in range(20):
        stream = open_member(path, info)
        assert stream is not None
        stream.close()
    assert len(list(Path("/proc/self/fd").iterdir())) == before
