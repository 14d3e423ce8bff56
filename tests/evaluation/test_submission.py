"""validate_submission: one test per bad submission, each asserting its message."""

from __future__ import annotations

import stat
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
        "alpha.labels: expected 120 lines (one per point of the scan), found 122",
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
