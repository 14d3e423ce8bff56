"""Downloading splits from a local HTTP mirror: landing, skipping, resuming, retrying, failing."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.core.errors import DownloadError
from semantic3d.datasets.download import (
    DOWNLOADS_DIRNAME,
    DownloadProgress,
    DownloadReport,
    IncompleteDownloadError,
    download_file,
    download_scans,
    download_split,
)
from semantic3d.datasets.registry import LABELS_ARCHIVE, Split, scan, scans
from semantic3d.datasets.semantic3d import Semantic3D

FAST = {"backoff_s": 0.0, "timeout_s": 10.0}


def leftovers(folder: Path) -> list[str]:
    """Anything in ``folder`` that is not a final scan file."""
    finals = {item.filename for info in scans() for item in info.files}
    return sorted(
        str(path.relative_to(folder)) for path in folder.rglob("*") if path.name not in finals
    )


def download_scans_of(name: str, folder: Path, mirror) -> DownloadReport:
    return download_scans([scan(name)], to=folder, base_url=mirror.base_url, **FAST)


def test_full_download_of_a_split(tmp_path: Path, full_mirror, benchmark_files) -> None:
    events: list[DownloadProgress] = []

    report = download_split(
        Split.REDUCED_8, to=tmp_path, base_url=full_mirror.base_url, progress=events.append, **FAST
    )

    assert [item.scan.name for item in report.downloaded] == [s.name for s in scans("reduced-8")]
    for info in scans(Split.REDUCED_8):
        landed = tmp_path / info.points.filename
        assert landed.read_bytes() == benchmark_files.contents[info.points.filename]
    assert Semantic3D(tmp_path).is_complete(Split.REDUCED_8)
    assert leftovers(tmp_path) == []
    finals = {event.filename: event for event in events if event.done_bytes == event.total_bytes}
    assert set(finals) == {info.points.archive_name for info in scans(Split.REDUCED_8)}


def test_training_split_renames_neugasse_and_shares_the_labels_archive(
    tmp_path: Path, full_mirror, benchmark_files
) -> None:
    download_split(Split.TRAIN, to=tmp_path, base_url=full_mirror.base_url, **FAST)

    neugasse = scan("neugasse_station1")
    assert (tmp_path / "neugasse_station1_xyz_intensity_rgb.txt").read_bytes() == (
        benchmark_files.contents[neugasse.points.filename]
    )
    assert not (tmp_path / "station1_xyz_intensity_rgb.txt").exists()
    for info in scans(Split.TRAIN):
        for item in info.files:
            assert (tmp_path / item.filename).read_bytes() == benchmark_files.contents[
                item.filename
            ]
    assert len(full_mirror.requests_for(LABELS_ARCHIVE)) == 1
    assert len(full_mirror.requests) == 16  # 15 point archives + 1 labels archive
    assert leftovers(tmp_path) == []


def test_complete_files_are_skipped(tmp_path: Path, full_mirror) -> None:
    download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, **FAST)
    full_mirror.requests.clear()

    again = download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, **FAST)

    assert full_mirror.requests == []
    assert len(again.skipped) == 4
    assert again.downloaded == ()


def test_only_the_missing_file_of_a_scan_is_fetched(tmp_path: Path, full_mirror) -> None:
    info = scan("bildstein_station1")
    assert info.labels is not None
    (tmp_path / info.points.filename).write_text("already here\n")

    report = download_scans_of(info.name, tmp_path, full_mirror)

    assert [seen.path for seen in full_mirror.requests] == [full_mirror.url_path(LABELS_ARCHIVE)]
    assert (tmp_path / info.points.filename).read_text() == "already here\n"
    assert (tmp_path / info.labels.filename).is_file()
    assert report.downloaded[0].paths == (
        tmp_path / info.points.filename,
        tmp_path / info.labels.filename,
    )


def test_interrupted_download_resumes_with_a_range_request(
    tmp_path: Path, full_mirror, benchmark_files
) -> None:
    info = scan("sg28_station2_reduced")
    archive = full_mirror.url_path(info.points.archive)
    full_mirror.script[archive] = ["cut"]
    size = len(full_mirror.files[archive])
    events: list[DownloadProgress] = []

    report = download_split(
        "reduced-8", to=tmp_path, base_url=full_mirror.base_url, progress=events.append, **FAST
    )

    seen = full_mirror.requests_for(info.points.archive)
    assert [request.range for request in seen] == [None, f"bytes={size // 2}-"]
    assert (tmp_path / info.points.filename).read_bytes() == (
        benchmark_files.contents[info.points.filename]
    )
    done = [event.done_bytes for event in events if event.filename == info.points.archive_name]
    assert done[-1] == size
    assert len(report.downloaded) == 4
    assert leftovers(tmp_path) == []


def test_part_file_left_by_an_earlier_run_is_continued(
    tmp_path: Path, full_mirror, benchmark_files
) -> None:
    info = scan("sg27_station10_reduced")
    data = full_mirror.files[full_mirror.url_path(info.points.archive)]
    part = tmp_path / DOWNLOADS_DIRNAME / (info.points.archive_name + ".part")
    part.parent.mkdir()
    part.write_bytes(data[:1000])

    download_scans_of(info.name, tmp_path, full_mirror)

    assert [r.range for r in full_mirror.requests_for(info.points.archive)] == ["bytes=1000-"]
    assert (tmp_path / info.points.filename).read_bytes() == (
        benchmark_files.contents[info.points.filename]
    )
    assert leftovers(tmp_path) == []


def test_server_ignoring_the_range_restarts_the_file(tmp_path: Path, full_mirror) -> None:
    info = scan("sg27_station10_reduced")
    url_path = full_mirror.url_path(info.points.archive)
    full_mirror.always[url_path] = "full"
    data = full_mirror.files[url_path]
    destination = tmp_path / "archive.7z"
    (tmp_path / "archive.7z.part").write_bytes(b"stale bytes from another file")

    download_file(full_mirror.base_url + info.points.archive, destination, **FAST)

    assert destination.read_bytes() == data
    assert not (tmp_path / "archive.7z.part").exists()


def test_complete_part_file_is_finished_on_http_416(tmp_path: Path, full_mirror) -> None:
    info = scan("sg27_station10_reduced")
    data = full_mirror.files[full_mirror.url_path(info.points.archive)]
    destination = tmp_path / "archive.7z"
    (tmp_path / "archive.7z.part").write_bytes(data)

    download_file(full_mirror.base_url + info.points.archive, destination, **FAST)

    assert destination.read_bytes() == data
    assert [r.range for r in full_mirror.requests] == [f"bytes={len(data)}-"]


def test_transient_errors_are_retried(tmp_path: Path, full_mirror, benchmark_files) -> None:
    info = scan("stgallencathedral_station6_reduced")
    url_path = full_mirror.url_path(info.points.archive)
    full_mirror.script[url_path] = ["503", "drop", "503"]

    download_scans_of(info.name, tmp_path, full_mirror)

    assert len(full_mirror.requests_for(info.points.archive)) == 4
    assert (tmp_path / info.points.filename).read_bytes() == (
        benchmark_files.contents[info.points.filename]
    )


def test_each_wait_before_a_retry_is_reported(tmp_path: Path, full_mirror) -> None:
    info = scan("stgallencathedral_station6_reduced")
    full_mirror.script[full_mirror.url_path(info.points.archive)] = ["503", "503"]
    events: list[DownloadProgress] = []

    download_file(
        full_mirror.base_url + info.points.archive,
        tmp_path / "archive.7z",
        progress=events.append,
        backoff_s=0.001,
        retries=3,
    )

    waits = [event.waiting for event in events if event.waiting is not None]
    assert waits == [
        "HTTP 503 Service Unavailable; retry 1/3 in 0 s",
        "HTTP 503 Service Unavailable; retry 2/3 in 0 s",
    ]
    assert events[-1].waiting is None and events[-1].done_bytes == events[-1].total_bytes


def test_a_host_that_does_not_resolve_fails_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import socket
    import time

    def no_address(*args: object, **kwargs: object) -> None:
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", no_address)
    started = time.monotonic()
    with pytest.raises(DownloadError, match=r"expected the host mirror\.example to resolve"):
        download_file("http://mirror.example/x.7z", tmp_path / "x.7z", retries=5, backoff_s=30)
    assert time.monotonic() - started < 5  # no backoff: 30 s would be the first wait
    assert not (tmp_path / "x.7z.part").exists()


def test_retries_run_out_and_the_error_names_the_scan(tmp_path: Path, full_mirror) -> None:
    info = scan("stgallencathedral_station6_reduced")
    full_mirror.always[full_mirror.url_path(info.points.archive)] = "503"

    with pytest.raises(IncompleteDownloadError) as caught:
        download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, retries=2, **FAST)

    assert len(full_mirror.requests_for(info.points.archive)) == 3
    assert [item.scan.name for item in caught.value.failures] == [info.name]
    message = str(caught.value)
    assert "1 of 4 scans failed" in message
    assert f"{info.name}: " in message
    assert "gave up after 3 failed attempts: HTTP 503" in message
    assert len(caught.value.report.downloaded) == 3


def test_missing_archive_fails_only_its_scan(tmp_path: Path, full_mirror) -> None:
    failing = scan("marketplacefeldkirch_station4_reduced")
    del full_mirror.files[full_mirror.url_path(failing.points.archive)]

    with pytest.raises(IncompleteDownloadError, match=f"{failing.name}: .*HTTP 404") as caught:
        download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, **FAST)

    assert len(full_mirror.requests_for(failing.points.archive)) == 1  # a 404 is not retried
    assert [item.scan.name for item in caught.value.failures] == [failing.name]
    assert isinstance(caught.value.failures[0].error, DownloadError)
    dataset = Semantic3D(tmp_path)
    assert [info.name for info in dataset.missing("reduced-8")] == [failing.name]
    assert not (tmp_path / failing.points.filename).exists()
    assert leftovers(tmp_path) == []


def test_failed_labels_archive_fails_every_training_scan_but_keeps_points(
    tmp_path: Path, full_mirror
) -> None:
    full_mirror.always[full_mirror.url_path(LABELS_ARCHIVE)] = "404"

    with pytest.raises(IncompleteDownloadError) as caught:
        download_split("train", to=tmp_path, base_url=full_mirror.base_url, **FAST)

    assert len(caught.value.failures) == 15
    assert all(LABELS_ARCHIVE in str(item.error) for item in caught.value.failures)
    assert len(list(tmp_path.glob("*.txt"))) == 15
    assert list(tmp_path.glob("*.labels")) == []


def test_corrupt_archive_leaves_nothing_under_final_names(tmp_path: Path, full_mirror) -> None:
    info = scan("sg28_station2_reduced")
    full_mirror.files[full_mirror.url_path(info.points.archive)] = b"not a 7z archive" * 100

    with pytest.raises(IncompleteDownloadError, match="not a readable 7z archive"):
        download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, **FAST)

    assert not (tmp_path / info.points.filename).exists()
    assert leftovers(tmp_path) == []  # the unreadable archive is dropped for a fresh retry


def test_connection_dropping_for_good_keeps_the_part_file(tmp_path: Path, full_mirror) -> None:
    info = scan("sg28_station2_reduced")
    url_path = full_mirror.url_path(info.points.archive)
    full_mirror.script[url_path] = ["cut", "drop", "drop"]

    with pytest.raises(IncompleteDownloadError, match="gave up after 2 failed attempts"):
        download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, retries=1, **FAST)

    assert not (tmp_path / info.points.filename).exists()
    part = tmp_path / DOWNLOADS_DIRNAME / (info.points.archive_name + ".part")
    assert part.stat().st_size == len(full_mirror.files[url_path]) // 2
    assert leftovers(tmp_path) == [DOWNLOADS_DIRNAME, str(part.relative_to(tmp_path))]


def test_hostile_archive_member_is_refused(tmp_path: Path, full_mirror, tools) -> None:
    info = scan("sg28_station2_reduced")
    full_mirror.files[full_mirror.url_path(info.points.archive)] = tools.build_hostile_7z(
        {info.points.member: b"0 0 0 0 0 0 0\n", "../../escaped.txt": b"owned\n"}
    )

    with pytest.raises(IncompleteDownloadError, match=r"unsafe member '\.\./\.\./escaped\.txt'"):
        download_split("reduced-8", to=tmp_path / "data", base_url=full_mirror.base_url, **FAST)

    assert not (tmp_path / "escaped.txt").exists()
    assert not (tmp_path.parent / "escaped.txt").exists()
    assert not (tmp_path / "data" / info.points.filename).exists()


def test_negative_retries_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="retries: expected a count >= 0, found -1"):
        download_split("train", to=tmp_path, retries=-1)


def test_unreachable_server_is_a_download_error(tmp_path: Path) -> None:
    with pytest.raises(DownloadError, match="gave up after 1 failed attempts: connection failed"):
        download_file("http://127.0.0.1:9/nothing.7z", tmp_path / "x.7z", retries=0, **FAST)


def test_a_file_url_mirror_works_too(tmp_path: Path, benchmark_files) -> None:
    root = tmp_path / "mirror"
    for archive, data in benchmark_files.archives.items():
        if archive.startswith("point-clouds/testing2/"):
            (root / archive).parent.mkdir(parents=True, exist_ok=True)
            (root / archive).write_bytes(data)
    out = tmp_path / "out"

    report = download_split("reduced-8", to=out, base_url=root.as_uri(), **FAST)

    assert len(report.downloaded) == 4
    for info in scans("reduced-8"):
        assert (out / info.points.filename).read_bytes() == (
            benchmark_files.contents[info.points.filename]
        )


def test_each_failed_scan_carries_an_error_naming_it(tmp_path: Path, full_mirror) -> None:
    for name in ("sg27_station10_reduced", "sg28_station2_reduced"):
        del full_mirror.files[full_mirror.url_path(scan(name).points.archive)]

    with pytest.raises(IncompleteDownloadError) as caught:
        download_split("reduced-8", to=tmp_path, base_url=full_mirror.base_url, **FAST)

    errors = {item.scan.name: str(item.error) for item in caught.value.failures}
    assert set(errors) == {"sg27_station10_reduced", "sg28_station2_reduced"}
    for name, message in errors.items():
        assert message.startswith(f"{name}: http://127.0.0.1:")
        assert message.endswith("HTTP 404 Not Found")
