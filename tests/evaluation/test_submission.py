"""validate_submission: one test per bad submission, each asserting its message."""

from __future__ import annotations

import io
import stat
import struct
import zipfile
from pathlib import Path

import pytest

from semantic3d.core.errors import SubmissionError
from semantic3d.evaluation import (
    SubmissionLimits,
    custom_challenge,
    load_challenge,
    validate_submission,
)
from semantic3d.evaluation.contents import READ_FAILURES, SubmissionFile, read_failure
from tests.budgets import Budget
from tests.evaluation.conftest import Scans, labels_bytes, write_zip


def _problems(submission: Path, scans: Scans, **kwargs: object) -> tuple[str, ...]:
    with pytest.raises(SubmissionError) as caught:
        validate_submission(
            submission,
            challenge=custom_challenge(scans.gt_dir),
            **kwargs,  # type: ignore[arg-type]
        )
    assert caught.value.source == str(submission)
    return caught.value.problems


def test_valid_zip_and_folder_pass(scans: Scans, tmp_path: Path) -> None:
    challenge = custom_challenge(scans.gt_dir)
    validate_submission(write_zip(tmp_path / "s.zip", scans.pred_members()), challenge=challenge)
    validate_submission(scans.pred_folder(tmp_path / "s"), challenge=challenge)


def test_progress_reaches_the_total(scans: Scans, tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    validate_submission(
        write_zip(tmp_path / "s.zip", scans.pred_members()),
        challenge=custom_challenge(scans.gt_dir),
        progress=lambda done, total: calls.append((done, total)),
    )
    total = sum(len(data) for data in scans.pred_members().values())
    assert calls[-1] == (total, total)


def test_wrong_case_gets_a_case_sensitive_hint(scans: Scans, tmp_path: Path) -> None:
    members = scans.pred_members()
    members["Alpha.labels"] = members.pop("alpha.labels")
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "unexpected file 'Alpha.labels' (names are case-sensitive: did you mean 'alpha.labels'?)",
        "missing file 'alpha.labels' (scan alpha)",
    )


def test_misspelt_name_gets_a_did_you_mean_hint(tmp_path: Path) -> None:
    challenge = load_challenge("reduced-8", ground_truth_root=None)
    members = {name: b"1\n" for name in challenge.submission_names}
    members["sg27_10_reduced.labels"] = members.pop("sg27_10-reduced.labels")
    with pytest.raises(SubmissionError) as caught:
        validate_submission(write_zip(tmp_path / "s.zip", members), challenge=challenge)
    problems = caught.value.problems
    assert (
        "unexpected file 'sg27_10_reduced.labels' (did you mean 'sg27_10-reduced.labels'?)"
        in problems
    )
    assert "missing file 'sg27_10-reduced.labels' (scan sg27_station10_rgb_intensity-reduced)" in (
        problems
    )
    # line counts come from the protocol when no ground truth is given
    assert (
        "marketsquarefeldkirch4-reduced.labels: expected 10538633 lines "
        "(one per point of the scan), found 1" in problems
    )


def test_missing_file(scans: Scans, tmp_path: Path) -> None:
    members = scans.pred_members()
    del members["beta.labels"]
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "missing file 'beta.labels' (scan beta)",
    )


def test_extra_file(scans: Scans, tmp_path: Path) -> None:
    members = {**scans.pred_members(), "readme.txt": b"hello"}
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "unexpected file 'readme.txt'",
    )


def test_wrong_line_count(scans: Scans, tmp_path: Path) -> None:
    members = scans.pred_members()
    members["alpha.labels"] += b"1\n1\n"
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "alpha.labels: expected 120 lines (one per point of the scan), found more than 121 "
        "(reading stopped there)",
    )


def test_truncated_file(scans: Scans, tmp_path: Path) -> None:
    members = scans.pred_members()
    members["alpha.labels"] = members["alpha.labels"][:101]  # 50 lines and half of one
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "alpha.labels: expected 120 lines (one per point of the scan), found 51",
    )
    folder = scans.pred_folder(tmp_path / "s", members)
    assert _problems(folder, scans) == (
        "alpha.labels: expected 120 lines (one per point of the scan), found 51",
    )


def test_non_integer_values(scans: Scans, tmp_path: Path) -> None:
    values = [str(v) for v in scans.pred["beta.labels"]]
    values[4], values[9], values[10] = "2.0", "car", ""
    members = {**scans.pred_members(), "beta.labels": ("\n".join(values) + "\n").encode()}
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "beta.labels: line 5: expected an integer label value 1..8, found '2.0' "
        "(2 more lines are not integers)",
    )


def test_zero_and_nine_are_out_of_range(scans: Scans, tmp_path: Path) -> None:
    values = scans.pred["alpha.labels"].copy()
    values[2], values[50] = 0, 9
    members = {**scans.pred_members(), "alpha.labels": labels_bytes(values)}
    assert _problems(write_zip(tmp_path / "s.zip", members), scans) == (
        "alpha.labels: line 3: expected an integer label value 1..8, found 0 "
        "(1 more line is out of range)",
    )


def test_crlf_is_accepted(scans: Scans, tmp_path: Path) -> None:
    members = {name: labels_bytes(v, crlf=True) for name, v in scans.pred.items()}
    validate_submission(
        write_zip(tmp_path / "s.zip", members), challenge=custom_challenge(scans.gt_dir)
    )


def test_one_top_level_folder_is_accepted(scans: Scans, tmp_path: Path) -> None:
    members = {f"my_results/{name}": data for name, data in scans.pred_members().items()}
    challenge = custom_challenge(scans.gt_dir)
    validate_submission(write_zip(tmp_path / "s.zip", members), challenge=challenge)
    validate_submission(scans.pred_folder(tmp_path / "s", members), challenge=challenge)


def test_macosx_metadata_is_ignored(scans: Scans, tmp_path: Path) -> None:
    members = {
        **{f"results/{name}": data for name, data in scans.pred_members().items()},
        "__MACOSX/results/._alpha.labels": b"\x00\x05\x16\x07",
        "results/.DS_Store": b"\x00\x00\x00\x01Bud1",
    }
    validate_submission(
        write_zip(tmp_path / "s.zip", members), challenge=custom_challenge(scans.gt_dir)
    )


def test_nested_folders_are_rejected(scans: Scans, tmp_path: Path) -> None:
    members = {**scans.pred_members(), "deep/er/alpha.labels": b"1\n"}
    problems = _problems(write_zip(tmp_path / "s.zip", members), scans)
    assert problems[0] == (
        "'deep/er/alpha.labels': expected label files at the top level or inside one folder, "
        "found a nested path"
    )


def test_declared_size_over_the_member_cap(scans: Scans, tmp_path: Path) -> None:
    members = {**scans.pred_members(), "alpha.labels": b"1\n" * 200_000}
    limits = SubmissionLimits(max_member_bytes=100_000)
    assert _problems(write_zip(tmp_path / "s.zip", members), scans, limits=limits) == (
        "'alpha.labels': uncompressed size 400000 bytes exceeds the limit of 100000 bytes",
    )


def test_zip_bomb_compression_ratio(scans: Scans, tmp_path: Path) -> None:
    bomb = b"1\n" * 5_000_000  # 10 MB of one line, bzip2 packs it > 20000:1
    path = tmp_path / "bomb.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("alpha.labels", bomb, compress_type=zipfile.ZIP_BZIP2)
        archive.writestr("beta.labels", scans.pred_members()["beta.labels"])
    (problem,) = _problems(path, scans)
    assert problem.startswith("'alpha.labels': compression ratio ")
    assert problem.endswith(":1 exceeds the limit of 2000:1 (zip bomb?)")


def test_total_size_cap(scans: Scans, tmp_path: Path) -> None:
    limits = SubmissionLimits(max_total_bytes=300)
    problems = _problems(write_zip(tmp_path / "s.zip", scans.pred_members()), scans, limits=limits)
    assert problems[0] == "total uncompressed size 400 bytes exceeds the limit of 300 bytes"


def test_inflating_past_the_declared_size_is_stopped(scans: Scans, tmp_path: Path) -> None:
    path = write_zip(tmp_path / "s.zip", scans.pred_members(), compression=zipfile.ZIP_STORED)
    # Forge the central directory: declare alpha.labels (240 bytes) as 10 bytes.
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        assert archive.infolist()[0].filename == "alpha.labels"
        assert archive.infolist()[0].file_size == 240
    central = data.find(b"PK\x01\x02")  # first central-directory record: alpha.labels
    data[central + 24 : central + 28] = (10).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    (problem,) = _problems(path, scans)
    assert problem.startswith("alpha.labels: corrupt archive member, reading failed (BadZipFile")


def test_path_traversal_and_absolute_paths(scans: Scans, tmp_path: Path) -> None:
    members = {**scans.pred_members(), "../alpha.labels": b"1\n", "/etc/beta.labels": b"1\n"}
    problems = _problems(write_zip(tmp_path / "s.zip", members), scans)
    assert problems == (
        "'../alpha.labels': path traversal ('..' component)",
        "'/etc/beta.labels': absolute path (expected paths relative to the archive root)",
    )


def test_symlink_member(scans: Scans, tmp_path: Path) -> None:
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("alpha.labels", scans.pred_members()["alpha.labels"])
        link = zipfile.ZipInfo("beta.labels")
        link.external_attr = (stat.S_IFLNK | 0o777) << 16
        archive.writestr(link, "/etc/passwd")
    assert _problems(path, scans) == ("'beta.labels': symbolic link (expected regular files)",)


def test_symlink_in_a_folder(scans: Scans, tmp_path: Path) -> None:
    folder = scans.pred_folder(tmp_path / "s")
    (folder / "beta.labels").unlink()
    (folder / "beta.labels").symlink_to(scans.gt_dir / "beta.labels")
    assert _problems(folder, scans) == ("'beta.labels': symbolic link (expected regular files)",)


def test_truncated_zip(scans: Scans, tmp_path: Path) -> None:
    path = write_zip(tmp_path / "s.zip", scans.pred_members())
    path.write_bytes(path.read_bytes()[:100])
    assert _problems(path, scans) == (
        "expected a zip archive or a folder of .labels files, found a corrupt or truncated "
        "zip archive (no central directory)",
    )


def test_corrupt_member_data(scans: Scans, tmp_path: Path) -> None:
    path = write_zip(tmp_path / "s.zip", scans.pred_members(), compression=zipfile.ZIP_STORED)
    data = bytearray(path.read_bytes())
    at = data.find(b"\n", 60)  # inside the first member's stored bytes
    data[at - 1] = ord("3") if data[at - 1] != ord("3") else ord("4")
    path.write_bytes(bytes(data))
    (problem,) = _problems(path, scans)
    assert problem == (
        "alpha.labels: corrupt archive member, reading failed (BadZipFile: "
        "Bad CRC-32 for file 'alpha.labels')"
    )


def test_not_a_zip(scans: Scans, tmp_path: Path) -> None:
    path = tmp_path / "s.tar"
    path.write_bytes(b"ustar\x00 this is not a zip")
    assert _problems(path, scans) == (
        "expected a zip archive or a folder of .labels files, found a file that is not a "
        "zip archive (starts with b'usta')",
    )


def test_nothing_there(scans: Scans, tmp_path: Path) -> None:
    assert _problems(tmp_path / "missing.zip", scans) == (
        "expected a zip archive or a folder, found nothing",
    )


def test_duplicate_member_names(scans: Scans, tmp_path: Path) -> None:
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w") as archive, pytest.warns(UserWarning, match="Duplicate"):
        for name, data in scans.pred_members().items():
            archive.writestr(name, data)
        archive.writestr("beta.labels", b"1\n")
    assert _problems(path, scans) == ("'beta.labels': appears 2 times in the archive",)


def test_every_problem_is_reported_at_once(scans: Scans, tmp_path: Path) -> None:
    alpha = scans.pred["alpha.labels"].copy()
    alpha[0] = 9
    members = {
        "results/alpha.labels": labels_bytes(alpha) + b"x\n",
        "results/Beta.labels": scans.pred_members()["beta.labels"],
        "results/notes.txt": b"hi",
        "../escape.labels": b"1\n",
        "__MACOSX/results/._alpha.labels": b"junk",
    }
    problems = _problems(write_zip(tmp_path / "s.zip", members), scans)
    assert problems == (
        "'../escape.labels': path traversal ('..' component)",
        "unexpected file 'Beta.labels' (names are case-sensitive: did you mean 'beta.labels'?)",
        "unexpected file 'notes.txt'",
        "missing file 'beta.labels' (scan beta)",
        "alpha.labels: line 121: expected an integer label value 1..8, found 'x'",
        "alpha.labels: line 1: expected an integer label value 1..8, found 9",
        "alpha.labels: expected 120 lines (one per point of the scan), found 121",
    )
    message = str(SubmissionError(problems, source="s.zip"))
    assert message.startswith("s.zip: invalid submission, 7 problems:\n  - ")


# Archive-index and read limits: bounded in CPU time and memory -----------------------------


def _many_entries_zip(
    path: Path, n_entries: int, *, declared: int | None = None, zip64: bool = False
) -> Path:
    """A zip of ``n_entries`` empty stored members, written directly (``writestr`` is slow).

    ``declared``: the member count written into the end record (a forged, smaller one);
    ``zip64``: add ZIP64 end records holding the counts (the classic record then says 0xFFFF).
    """
    local, central = [], []
    offset = 0
    for i in range(n_entries):
        name = b"%07d.labels" % i
        local.append(struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, 0, 0, 0, 0, 0, 0, len(name), 0))
        local.append(name)
        central.append(
            struct.pack(
                "<4s6H3L5H2L",
                b"PK\x01\x02",
                20,
                20,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                len(name),
                0,
                0,
                0,
                0,
                0,
                offset,
            )
        )
        central.append(name)
        offset += 30 + len(name)
    directory = b"".join(central)
    count = n_entries if declared is None else declared
    tail = b""
    if zip64:
        at = offset + len(directory)
        tail = struct.pack(
            "<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, count, count, len(directory), offset
        ) + struct.pack("<4sLQL", b"PK\x06\x07", 0, at, 1)
        count = 0xFFFF
    end = struct.pack(
        "<4s4H2LH",
        b"PK\x05\x06",
        0,
        0,
        min(count, 0xFFFF),
        min(count, 0xFFFF),
        len(directory),
        offset,
        0,
    )
    path.write_bytes(b"".join(local) + directory + tail + end)
    return path


def _bounded_problems(
    submission: Path, scans: Scans, **kwargs: object
) -> tuple[tuple[str, ...], float, float]:
    """The problems, the CPU seconds and the peak traced MB of validating ``submission``.

    Two runs: one timed (tracing allocations slows Python's allocations several times),
    one traced."""
    with Budget(traced=False) as timed:
        problems = _problems(submission, scans, **kwargs)
    with Budget() as traced:
        assert _problems(submission, scans, **kwargs) == problems
    return problems, timed.cpu_s, traced.peak_mb


@pytest.mark.parametrize(
    ("declared", "zip64"),
    [(None, False), (1, False), (None, True)],
    ids=["count", "forged", "zip64"],
)
def test_member_cap_is_checked_before_the_index_is_built(
    scans: Scans, tmp_path: Path, declared: int | None, zip64: bool
) -> None:
    # 100,000 entries: building zipfile's index of them takes ~1.5 s and ~50 MB here
    # (1 M entries: 15 s CPU, +470 MB); the end record and a bounded walk take milliseconds.
    path = _many_entries_zip(tmp_path / "many.zip", 100_000, declared=declared, zip64=zip64)
    problems, cpu_s, peak_mb = _bounded_problems(path, scans)
    if declared is None:  # the classic end record holds at most 65535
        count = 100_000 if zip64 else 65_535
        assert problems == (f"archive holds {count} members, more than the limit of 10000",)
    else:  # the end record understates the count: the walk stops at the 10,001st entry
        assert problems == ("archive holds more than 10000 members, more than the limit of 10000",)
    assert peak_mb < 12, f"{peak_mb:.1f} MB traced"
    # What building the index costs in this process, measured the same way.
    with Budget(traced=False) as index, zipfile.ZipFile(path) as archive:
        assert len(archive.infolist()) == 100_000
    assert cpu_s < 0.25 * index.cpu_s, f"{cpu_s:.3f} s CPU; the index {index.cpu_s:.3f} s"


def test_oversized_central_directory_is_refused_unread(scans: Scans, tmp_path: Path) -> None:
    path = _many_entries_zip(tmp_path / "many.zip", 20_000, declared=5)
    limits = SubmissionLimits(max_directory_bytes=100_000)
    problems, cpu_s, peak_mb = _bounded_problems(path, scans, limits=limits)
    assert problems == (
        "central directory of 1200000 bytes, more than the limit of 100000 bytes "
        "(too many members or overlong names)",
    )
    assert cpu_s < 0.1 and peak_mb < 1


def test_archives_under_the_cap_still_open(scans: Scans, tmp_path: Path) -> None:
    path = _many_entries_zip(tmp_path / "many.zip", 50)
    problems = _problems(path, scans, limits=SubmissionLimits(max_members=50))
    assert "unexpected file '0000000.labels'" in problems


@pytest.mark.parametrize("twin", ["d//beta.labels", "d/./beta.labels", "d\\beta.labels"])
def test_duplicates_are_found_after_normalising_names(
    scans: Scans, tmp_path: Path, twin: str
) -> None:
    members = {f"d/{name}": data for name, data in scans.pred_members().items()}
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
        archive.writestr(twin, b"1\n")
    assert _problems(path, scans) == ("'d/beta.labels': appears 2 times in the archive",)


def test_reading_stops_one_line_past_the_expected_count(scans: Scans, tmp_path: Path) -> None:
    # 960 short lines where 120 are expected: within the bytes 121 lines may take, so the
    # file is read, and reading stops at line 121.
    members = scans.pred_members()
    members["alpha.labels"] = b"1\n" * 960
    path = write_zip(tmp_path / "long.zip", members)
    problems = _problems(path, scans)
    assert problems == (
        "alpha.labels: expected 120 lines (one per point of the scan), found more than 121 "
        "(reading stopped there)",
    )


@pytest.mark.parametrize(
    "content", [b"1\n" * (32 << 20), b"1" * (64 << 20)], ids=["lines", "no-newline"]
)
def test_more_bytes_than_the_lines_can_take_are_refused_unread(
    scans: Scans, tmp_path: Path, content: bytes
) -> None:
    # 64 MiB where 120 lines (at most 121 x 16 bytes) are expected. Reading it all (the
    # old behaviour) inflates and parses every byte, ~0.3 s CPU here (2 GiB: 10-24 s);
    # without a line end, counting lines never stops early.
    members = scans.pred_members()
    members["alpha.labels"] = content
    path = tmp_path / "long.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    del members
    problems, cpu_s, peak_mb = _bounded_problems(path, scans)
    assert problems == (
        "alpha.labels: 67108864 bytes once inflated, more than 120 lines can take (at most "
        "1936 bytes, 16 a line); not read",
    )
    # (the other, valid file is parsed through a 4 MiB block buffer)
    assert cpu_s < 0.05 and peak_mb < 8, f"{cpu_s:.3f} s CPU, {peak_mb:.1f} MB traced"


def test_a_stream_is_never_read_past_its_byte_cap() -> None:
    # The declared size is checked first; the cap also holds for a file that grows (or a
    # member that inflates to more) after it was sized.
    entry = SubmissionFile("a.labels", "a.labels", 10, lambda: io.BytesIO(b"1" * 4000))
    with entry.open(max_bytes=1936) as handle, pytest.raises(READ_FAILURES) as caught:
        while handle.read(1000):
            pass
    assert read_failure("a.labels", caught.value) == (
        "a.labels: inflates to more than 1936 bytes once inflated (zip bomb?), reading stopped"
    )
