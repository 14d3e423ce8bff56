"""Safe 7z extraction: member-name checks, atomic landing, nothing half-written."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.core.errors import DownloadError
from semantic3d.datasets.archive import check_member_name, extract_members


@pytest.mark.parametrize(
    "name",
    [
        "../escape.txt",
        "data/../../escape.txt",
        "/etc/escape.txt",
        "..\\escape.txt",
        "C:\\Windows\\escape.txt",
        "C:escape.txt",
        "\\\\server\\share\\escape.txt",
        "",
    ],
)
def test_unsafe_member_names_are_refused(name: str) -> None:
    with pytest.raises(
        DownloadError, match=r"scan\.7z: unsafe member .*: expected a relative path"
    ):
        check_member_name(name, archive="scan.7z")


@pytest.mark.parametrize("name", ["scan.txt", "folder/scan.txt", "scan..txt", "..scan.txt"])
def test_safe_member_names_pass(name: str) -> None:
    check_member_name(name, archive="scan.7z")


def test_extracts_chosen_members_under_final_names(tmp_path: Path, tools) -> None:
    content = tools.scan_text("a")
    archive = tmp_path / "a.7z"
    archive.write_bytes(tools.build_7z({"station1.txt": content, "other.txt": b"1\n"}))
    out = tmp_path / "out"

    landed = extract_members(archive, {"station1.txt": out / "neugasse_station1.txt"})

    assert landed == [out / "neugasse_station1.txt"]
    assert (out / "neugasse_station1.txt").read_bytes() == content
    assert sorted(path.name for path in out.iterdir()) == ["neugasse_station1.txt"]


def test_extracts_several_members_in_one_pass(tmp_path: Path, tools) -> None:
    members = {f"scan{i}.labels": tools.labels_text(str(i)) for i in range(3)}
    archive = tmp_path / "labels.7z"
    archive.write_bytes(tools.build_7z(members))

    extract_members(archive, {name: tmp_path / name for name in members})

    for name, data in members.items():
        assert (tmp_path / name).read_bytes() == data


@pytest.mark.parametrize("evil", ["../evil.txt", "/tmp/semantic3d-evil.txt", "sub/../../evil.txt"])
def test_archive_with_escaping_member_is_refused_whole(tmp_path: Path, tools, evil: str) -> None:
    archive = tmp_path / "hostile.7z"
    archive.write_bytes(tools.build_hostile_7z({"scan.txt": b"1 2 3 4 5 6 7\n", evil: b"owned\n"}))
    out = tmp_path / "out"
    out.mkdir()

    with pytest.raises(DownloadError, match=r"hostile\.7z: unsafe member"):
        extract_members(archive, {"scan.txt": out / "scan.txt"})

    assert list(out.iterdir()) == []
    assert not (tmp_path / "evil.txt").exists()
    assert not Path("/tmp/semantic3d-evil.txt").exists()


def test_missing_member_names_what_was_expected_and_found(tmp_path: Path, tools) -> None:
    archive = tmp_path / "a.7z"
    archive.write_bytes(tools.build_7z({"station1_xyz_intensity_rgb.txt": b"0 0 0 0 0 0 0\n"}))

    with pytest.raises(
        DownloadError,
        match=r"a\.7z: expected member\(s\) neugasse\.txt, found station1_xyz_intensity_rgb\.txt",
    ):
        extract_members(archive, {"neugasse.txt": tmp_path / "neugasse.txt"})
    assert not (tmp_path / "neugasse.txt").exists()


def test_garbage_is_not_a_readable_archive(tmp_path: Path) -> None:
    archive = tmp_path / "garbage.7z"
    archive.write_bytes(b"<html>Service moved</html>" * 10)

    with pytest.raises(DownloadError, match=r"garbage\.7z: not a readable 7z archive"):
        extract_members(archive, {"scan.txt": tmp_path / "scan.txt"})
    assert not (tmp_path / "scan.txt").exists()


def test_truncated_archive_leaves_nothing_under_the_final_name(tmp_path: Path, tools) -> None:
    data = tools.build_7z({"scan.txt": tools.scan_text("big", n_points=20_000)})
    archive = tmp_path / "cut.7z"
    archive.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    out.mkdir()

    with pytest.raises(DownloadError, match=r"cut\.7z"):
        extract_members(archive, {"scan.txt": out / "scan.txt"})
    assert list(out.iterdir()) == []


def test_corrupted_payload_fails_its_check_and_leaves_nothing(tmp_path: Path, tools) -> None:
    data = bytearray(tools.build_7z({"scan.txt": tools.scan_text("crc", n_points=5_000)}))
    data[64] ^= 0xFF  # flip a byte inside the compressed stream
    archive = tmp_path / "flipped.7z"
    archive.write_bytes(bytes(data))
    out = tmp_path / "out"
    out.mkdir()

    with pytest.raises(DownloadError, match=r"flipped\.7z"):
        extract_members(archive, {"scan.txt": out / "scan.txt"})
    assert list(out.iterdir()) == []
