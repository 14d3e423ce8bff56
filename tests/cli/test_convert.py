from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.cli.console import guarded
from semantic3d.io.ascii import write_ascii_points
from semantic3d.io.formats import read_points, write_points
from semantic3d.io.labels import read_labels, write_labels
from semantic3d.io.las import read_las
from tests.factories import random_cloud

runner = CliRunner()


@pytest.fixture
def scan(tmp_path: Path) -> Path:
    """A labelled ASCII scan with its sibling ``.labels`` file, georeferenced."""
    path = tmp_path / "scan.txt"
    write_ascii_points(
        path, [random_cloud(2500, seed=21, offset=870_000.0)], labels_path=tmp_path / "scan.labels"
    )
    return path


def test_ascii_to_las_takes_the_sibling_labels(scan: Path, tmp_path: Path) -> None:
    result = runner.invoke(
        app, ["convert", str(scan), str(tmp_path / "out.laz"), "--chunk-size", "700"]
    )
    assert result.exit_code == 0, result.output
    assert "wrote 2,500 points to" in result.stdout and "with labels" in result.stdout
    assert read_las(tmp_path / "out.laz").equals(read_points(scan))


def test_las_to_ascii_writes_the_labels_beside(scan: Path, tmp_path: Path) -> None:
    runner.invoke(app, ["convert", str(scan), str(tmp_path / "out.las")])
    result = runner.invoke(app, ["convert", str(tmp_path / "out.las"), str(tmp_path / "back.txt")])
    assert result.exit_code == 0, result.output
    assert "their labels to" in result.stdout and "back.labels" in result.stdout
    assert (tmp_path / "back.txt").read_bytes() == scan.read_bytes()  # byte for byte
    assert (tmp_path / "back.labels").read_bytes() == (tmp_path / "scan.labels").read_bytes()


def test_labels_option_supplies_the_labels(tmp_path: Path) -> None:
    cloud = random_cloud(100, seed=3, labels=False)
    write_points(tmp_path / "points.ply", [cloud])
    labels = np.arange(100, dtype=np.uint8) % 9
    write_labels(tmp_path / "truth.labels", [labels])
    result = runner.invoke(
        app,
        [
            "convert",
            str(tmp_path / "points.ply"),
            str(tmp_path / "out.xyz"),
            "--labels",
            str(tmp_path / "truth.labels"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert np.array_equal(read_labels(tmp_path / "out.labels"), labels)


def test_convert_to_a_cache_folder_and_back(scan: Path, tmp_path: Path) -> None:
    result = runner.invoke(app, ["convert", str(scan), str(tmp_path / "scan.cache")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "scan.cache" / "meta.json").is_file()
    result = runner.invoke(
        app, ["convert", str(tmp_path / "scan.cache"), str(tmp_path / "copy.ply")]
    )
    assert result.exit_code == 0, result.output
    assert read_points(tmp_path / "copy.ply").equals(read_points(scan))


@pytest.mark.parametrize(
    ("make_args", "message"),
    [
        (
            lambda d: ["convert", str(d / "scan.txt"), str(d / "out.csv")],
            "expected a point file ending in one of",
        ),
        (
            lambda d: ["convert", str(d / "scan.txt"), str(d / "scan.txt")],
            "output is the input file",
        ),
        (lambda d: ["convert", str(d / "bad.las"), str(d / "out.ply")], "expected a LAS/LAZ file"),
        (lambda d: ["info", str(d / "notes.md")], "expected a point file ending in one of"),
        (
            lambda d: ["convert", str(d / "scan.txt"), str(d / "scan.xyz")],
            "output labels would overwrite the input labels",
        ),
    ],
)
def test_bad_inputs_print_one_red_line_and_exit_2(
    scan: Path, tmp_path: Path, make_args: Callable[[Path], list[str]], message: str
) -> None:
    (tmp_path / "bad.las").write_bytes(b"garbage" * 50)
    (tmp_path / "notes.md").write_text("hello")
    result = runner.invoke(app, make_args(tmp_path))
    assert result.exit_code == 2
    assert message in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:")


def test_truncated_input_fails_cleanly_and_leaves_no_output(scan: Path, tmp_path: Path) -> None:
    runner.invoke(app, ["convert", str(scan), str(tmp_path / "full.laz")])
    data = (tmp_path / "full.laz").read_bytes()
    (tmp_path / "cut.laz").write_bytes(data[: len(data) // 2])
    result = runner.invoke(app, ["convert", str(tmp_path / "cut.laz"), str(tmp_path / "out.ply")])
    assert result.exit_code == 2
    assert "cut.laz: expected 2500 points" in result.stderr
    assert not (tmp_path / "out.ply").exists()


def test_info_shows_count_bounds_columns_and_classes(scan: Path) -> None:
    cloud = read_points(scan)
    result = runner.invoke(app, ["info", str(scan), "--chunk-size", "1000"])
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "2,500" in out
    assert f"{cloud.xyz[:, 0].min():.3f}" in out and f"{cloud.xyz[:, 0].max():.3f}" in out
    assert "intensity text" in out and "label text (in scan.labels)" in out
    assert cloud.labels is not None
    counts = np.bincount(cloud.labels, minlength=9)
    for name, value in [("man-made terrain", 1), ("cars", 8), ("unlabelled", 0)]:
        line = next(row for row in out.splitlines() if name in row)
        assert f"{counts[value]:,}" in line


def test_info_on_an_unlabelled_las_file(tmp_path: Path) -> None:
    write_points(tmp_path / "plain.las", [random_cloud(10, labels=False)])
    result = runner.invoke(app, ["info", str(tmp_path / "plain.las")])
    assert result.exit_code == 0, result.output
    assert "semantic3d_intensity int32" in result.stdout
    assert "labels" in result.stdout and "none" in result.stdout
    assert "share" not in result.stdout  # no histogram table


def test_info_on_a_real_sample(shared_data: Path) -> None:
    path = shared_data / "ign-lidarhd-toy" / "870000_6618000_subset.txt"
    if not path.is_file():
        pytest.skip("IGN sample not available")
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    assert "70,840" in result.stdout and "buildings" in result.stdout
    assert "870200.010" in result.stdout  # georeferenced bounds to the millimetre


def _interrupt_a_conversion(tmp_path: Path, n_points: int) -> tuple[int, bytes]:
    """Start ``semantic3d convert`` and send it SIGINT once the partial output has content."""
    source = tmp_path / "big.txt"
    write_ascii_points(
        source, [random_cloud(n_points, seed=5)], labels_path=tmp_path / "big.labels"
    )
    destination = tmp_path / "out.las"
    destination.write_bytes(b"the previous output")
    # A process started with SIGINT ignored (a background job, setsid, some CI runners)
    # passes that on, and Python then never raises KeyboardInterrupt: the command gets
    # Python's own handler, as it would in a terminal. Set in the child itself, not by a
    # preexec_fn (Python code between fork and exec in this threaded test process could
    # wait for ever on a lock another thread held at the fork).
    entry = (
        "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from semantic3d.cli.app import main; main()"
    )
    command = [sys.executable, "-c", entry, "convert", str(source), str(destination)]
    process = subprocess.Popen(
        [*command, "--chunk-size", "2000", "--overwrite"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        # Interrupt once points are being written (the partial file has content), as a
        # user's Ctrl-C mid-way would.
        while not any(p.stat().st_size > 0 for p in tmp_path.glob(".out.*.partial.las")):
            if process.poll() is not None:
                break
            assert time.monotonic() < deadline, "no partial file seen"
            time.sleep(0.01)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
    return process.returncode, stderr


@pytest.mark.parametrize("suite_sigint", ["default", "ignored"])
def test_ctrl_c_exits_130_and_leaves_the_destination_as_it_was(
    tmp_path: Path, suite_sigint: str
) -> None:
    """A real SIGINT to a real ``semantic3d convert`` process, mid-way through the output,
    also when the suite itself runs with SIGINT ignored (``setsid``, a background job, some
    CI runners), which every child it starts would inherit."""
    if suite_sigint == "ignored":
        if threading.current_thread() is not threading.main_thread():
            pytest.skip("signal dispositions are set from the main thread only")
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        # On a loaded machine the conversion may finish before the signal lands; that run
        # proves nothing, so the next one is four times longer.
        for attempt, n_points in enumerate((400_000, 1_600_000, 6_400_000)):
            folder = tmp_path / str(attempt)
            folder.mkdir()
            returncode, stderr = _interrupt_a_conversion(folder, n_points)
            if returncode != 0:
                break
    finally:
        if suite_sigint == "ignored":
            signal.signal(signal.SIGINT, previous)
    assert returncode == 130, stderr.decode()
    assert b"Traceback" not in stderr
    assert (folder / "out.las").read_bytes() == b"the previous output"
    assert sorted(p.name for p in folder.iterdir()) == ["big.labels", "big.txt", "out.las"]


def test_interrupt_inside_a_compiled_kernel_is_an_interrupt() -> None:
    # numba reports a Ctrl-C during a kernel as SystemError caused by KeyboardInterrupt.
    with pytest.raises(KeyboardInterrupt), guarded():
        raise SystemError("returned a result with an exception set") from KeyboardInterrupt()
    with pytest.raises(SystemError), guarded():
        raise SystemError("a real bug")


@pytest.mark.parametrize(
    ("output", "existing"),
    [("out.las", ["out.las"]), ("out.txt", ["out.labels"]), ("out.cache", ["out.cache/x"])],
)
def test_an_existing_output_is_refused_unless_overwrite(
    scan: Path, tmp_path: Path, output: str, existing: list[str]
) -> None:
    for name in existing:
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"precious")
    result = runner.invoke(app, ["convert", str(scan), str(tmp_path / output)])
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "already exists" in lines[0] and "--overwrite" in lines[0]
    assert all((tmp_path / name).read_bytes() == b"precious" for name in existing)
    if output != "out.cache":  # a folder that is not a cache is never replaced
        result = runner.invoke(app, ["convert", str(scan), str(tmp_path / output), "--overwrite"])
        assert result.exit_code == 0, result.output
        assert read_points(tmp_path / output).equals(read_points(scan))


def test_an_empty_folder_is_not_an_existing_cache(scan: Path, tmp_path: Path) -> None:
    (tmp_path / "out.cache").mkdir()
    result = runner.invoke(app, ["convert", str(scan), str(tmp_path / "out.cache")])
    assert result.exit_code == 0, result.output


def test_a_missing_output_folder_is_created(scan: Path, tmp_path: Path) -> None:
    destination = tmp_path / "out" / "missing-dir" / "y.las"
    result = runner.invoke(app, ["convert", str(scan), str(destination)])
    assert result.exit_code == 0, result.output
    assert read_las(destination).equals(read_points(scan))


def test_an_unwritable_output_folder_is_one_line(scan: Path, tmp_path: Path) -> None:
    (tmp_path / "file").write_text("not a folder")
    result = runner.invoke(app, ["convert", str(scan), str(tmp_path / "file" / "y.las")])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "file" in lines[0]
    assert "Traceback" not in result.output


def test_crs_is_written_to_las(scan: Path, tmp_path: Path) -> None:
    pytest.importorskip("pyproj")
    import laspy

    out = tmp_path / "georef.laz"
    result = runner.invoke(app, ["convert", str(scan), str(out), "--crs", "EPSG:2154"])
    assert result.exit_code == 0, result.output
    with laspy.open(out) as reader:
        assert reader.header.global_encoding.wkt
        assert reader.header.parse_crs().to_epsg() == 2154


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["out.las", "--crs", "EPSG:99999999"], "expected a coordinate reference system"),
        (["out.ply", "--crs", "EPSG:2154"], "--crs applies to .las/.laz output"),
    ],
)
def test_bad_crs_is_one_line(scan: Path, tmp_path: Path, args: list[str], message: str) -> None:
    pytest.importorskip("pyproj")
    result = runner.invoke(app, ["convert", str(scan), str(tmp_path / args[0]), *args[1:]])
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0]
    assert not (tmp_path / args[0]).exists()


def test_many_sources_into_a_folder(scan: Path, tmp_path: Path) -> None:
    other = tmp_path / "other.ply"
    write_points(other, [random_cloud(700, seed=4)])
    out = tmp_path / "out"
    result = runner.invoke(
        app, ["convert", str(scan), str(other), "--out", str(out), "--to", "txt"]
    )
    assert result.exit_code == 0, result.output
    assert sorted(path.name for path in out.iterdir()) == [
        "other.labels",
        "other.txt",
        "scan.labels",
        "scan.txt",
    ]
    assert read_points(out / "scan.txt").equals(read_points(scan))
    assert read_points(out / "other.txt").n_points == 700
    assert f"wrote 2,500 points to {out / 'scan.txt'} and their labels" in result.stdout
    before = (out / "scan.txt").read_bytes()
    again = runner.invoke(app, ["convert", str(scan), str(other), "--out", str(out), "--to", "txt"])
    assert again.exit_code == 2
    assert "already exists (and 3 other outputs); pass --overwrite" in again.stderr
    assert (out / "scan.txt").read_bytes() == before


@pytest.mark.parametrize(
    ("make_args", "message"),
    [
        (lambda d: ["convert", str(d / "scan.txt")], "expected SOURCE DESTINATION, or SOURCE..."),
        (
            lambda d: ["convert", str(d / "scan.txt"), str(d / "a.las"), str(d / "b.las")],
            "found 3 paths and no --out",
        ),
        (lambda d: ["convert", str(d / "scan.txt"), "--out", str(d / "o")], "--to: expected one"),
        (
            lambda d: ["convert", str(d / "scan.txt"), "--out", str(d / "o"), "--to", "csv"],
            "--to: expected one of txt, xyz, las, laz, ply, cache, found 'csv'",
        ),
        (
            lambda d: ["convert", str(d / "scan.txt"), str(d / "a.las"), "--to", "ply"],
            "--to applies with --out DIR",
        ),
        (
            lambda d: [
                "convert",
                str(d / "scan.txt"),
                str(d / "scan.ply"),
                "--out",
                str(d / "o"),
                "--to",
                "las",
            ],
            "scan.las: the output of both",
        ),
        (
            lambda d: ["convert", str(d / "gone.txt"), "--out", str(d / "o"), "--to", "las"],
            "gone.txt: expected a point file or cache folder, found nothing",
        ),
        (
            lambda d: [
                "convert",
                str(d / "scan.txt"),
                str(d / "other.ply"),
                "--out",
                str(d / "o"),
                "--to",
                "las",
                "--labels",
                str(d / "scan.labels"),
            ],
            "--labels applies to one source converted in this process",
        ),
    ],
)
def test_bad_many_file_forms_are_one_line(
    scan: Path, tmp_path: Path, make_args: Callable[[Path], list[str]], message: str
) -> None:
    for name in ("scan.ply", "other.ply"):
        write_points(tmp_path / name, [random_cloud(10, seed=1)])
    result = runner.invoke(app, make_args(tmp_path))
    assert result.exit_code == 2, result.output
    assert message in result.stderr
    assert not (tmp_path / "o").exists()
