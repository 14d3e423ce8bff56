"""Which labels a session reads and writes, and where its caches go (never beside the scan)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.core.errors import OutputExistsError
from semantic3d.io import read_labels
from semantic3d.labelling.cachedir import CACHE_DIR_ENV
from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.opening import (
    LabelsOutput,
    labels_output_state,
    open_label_session,
    plan_labels,
)

from .conftest import NODE_CAPACITY


@pytest.fixture
def scan_folder(simulated_scan, tmp_path) -> Path:
    """A copy of the simulated scan as ``scan.txt`` with its ground truth ``scan.labels``."""
    folder = tmp_path / "data"
    folder.mkdir()
    shutil.copyfile(simulated_scan.points_path, folder / "scan.txt")
    shutil.copyfile(simulated_scan.truth_path, folder / "scan.labels")
    return folder


def _listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def test_the_default_never_writes_over_the_scans_labels(scan_folder, tmp_path) -> None:
    scan = scan_folder / "scan.txt"
    truth = (scan_folder / "scan.labels").read_bytes()
    plan = plan_labels(scan)
    assert plan.output == scan_folder / "scan.edit.labels"
    assert plan.start_from == scan_folder / "scan.labels"
    assert "starting from" in plan.describe() and "read-only" in plan.describe()
    before = _listing(scan_folder)
    session = open_label_session(
        scan, labels_path=plan.output, start_from=plan.start_from, node_capacity=NODE_CAPACITY
    )
    np.testing.assert_array_equal(session.labels, read_labels(scan_folder / "scan.labels"))
    session.reset()
    session.assign(3, confirm_whole_scan=True)
    session.save()
    session.close()
    assert (scan_folder / "scan.labels").read_bytes() == truth
    # Only the output and its journal appeared: no cache, no level of detail beside the scan.
    added = _listing(scan_folder) - before
    assert {name for name in added if not name.startswith("scan.edit.labels.journal")} == {
        "scan.edit.labels"
    }
    # Next time the edit file is this session's own output: it is resumed, not refused.
    assert labels_output_state(plan.output) is LabelsOutput.OURS
    again = plan_labels(scan)
    assert again.output == plan.output and again.state is LabelsOutput.OURS
    resumed = open_label_session(scan, labels_path=again.output, node_capacity=NODE_CAPACITY)
    assert len(resumed.undo_stack) == 2 and (resumed.labels == 3).all()
    resumed.close()


def test_an_existing_file_is_written_only_when_told(scan_folder) -> None:
    scan = scan_folder / "scan.txt"
    truth_path = scan_folder / "scan.labels"
    truth = truth_path.read_bytes()
    with pytest.raises(OutputExistsError, match="pass --overwrite"):
        plan_labels(scan, labels=truth_path)
    with pytest.raises(OutputExistsError, match="not written by a labelling session"):
        open_label_session(scan, labels_path=truth_path, node_capacity=NODE_CAPACITY)
    assert truth_path.read_bytes() == truth and not list(scan_folder.glob("*.journal"))
    plan = plan_labels(scan, labels=truth_path, overwrite=True)
    assert plan.start_from is None and "in place" in plan.describe()
    session = open_label_session(
        scan, labels_path=truth_path, overwrite=True, node_capacity=NODE_CAPACITY
    )
    np.testing.assert_array_equal(session.labels, read_labels(truth_path))
    session.close()
    # A scan without labels: its NAME.labels is created (nothing is there to lose).
    bare = scan_folder / "bare.txt"
    shutil.copyfile(scan, bare)
    assert plan_labels(bare).output == scan_folder / "bare.labels"
    assert plan_labels(bare).start_from is None


def test_a_read_only_scan_folder_asks_for_labels(scan_folder, monkeypatch, tmp_path) -> None:
    real_access = os.access
    monkeypatch.setattr(
        "semantic3d.labelling.opening.os.access",
        lambda path, mode: False if Path(path) == scan_folder else real_access(path, mode),
    )
    with pytest.raises(OperationError, match="not writable; pass --labels"):
        plan_labels(scan_folder / "scan.txt")
    plan = plan_labels(scan_folder / "scan.txt", labels=tmp_path / "mine.labels")
    assert plan.output == tmp_path / "mine.labels"
    assert plan.start_from == scan_folder / "scan.labels"


def test_caches_are_keyed_by_path_and_rebuilt_when_the_scan_changes(
    scan_folder, tmp_path, labelling_cache_dir
) -> None:
    other = tmp_path / "other"
    other.mkdir()
    lines = (scan_folder / "scan.txt").read_text().splitlines(keepends=True)
    (other / "scan.txt").write_text("".join(lines[:5000]))  # same name, another scan
    first = open_label_session(scan_folder / "scan.txt", read_only=True)
    second = open_label_session(other / "scan.txt", read_only=True)
    assert first.n_points == len(lines) and second.n_points == 5000
    assert first.scan.path != second.scan.path
    assert labelling_cache_dir in first.scan.path.parents
    assert labelling_cache_dir in second.lod.directory.parents
    first.close()
    second.close()
    (other / "scan.txt").write_text("".join(lines[:7000]))
    changed = open_label_session(other / "scan.txt", read_only=True)
    assert changed.n_points == 7000 and changed.lod.n_points == 7000
    changed.close()
    assert _listing(other) == {"scan.txt"}


def test_a_level_of_detail_of_an_older_format_is_replaced(scan_folder, tmp_path) -> None:
    """An index of an older format version in the cache folder is rebuilt under the new
    version's name and the old one removed (1.7 GB at 10**8 points)."""
    from semantic3d.labelling.cachedir import entry_name
    from semantic3d.labelling.lod import LOD_VERSION

    caches = tmp_path / "caches"
    first = open_label_session(scan_folder / "scan.txt", read_only=True, cache_dir=caches)
    current = first.lod.directory
    first.close()
    older = caches / f"{entry_name(first.scan.path)}.lod-v1"
    assert current.name.endswith(f".lod-v{LOD_VERSION}") and LOD_VERSION > 1
    shutil.copytree(current, older)
    again = open_label_session(scan_folder / "scan.txt", read_only=True, cache_dir=caches)
    assert again.lod.directory == current and not older.exists()
    again.close()


def test_the_cache_folder_is_the_option_then_the_variable_then_the_users(
    scan_folder, tmp_path, monkeypatch
) -> None:
    from semantic3d.labelling.cachedir import default_cache_dir

    explicit = tmp_path / "explicit"  # --cache-dir
    session = open_label_session(scan_folder / "scan.txt", read_only=True, cache_dir=explicit)
    assert explicit in session.scan.path.parents and explicit in session.lod.directory.parents
    session.close()
    assert _listing(scan_folder) == {"scan.txt", "scan.labels"}
    monkeypatch.delenv(CACHE_DIR_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "semantic3d"  # platformdirs' user cache


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_cli_refuses_ground_truth_with_one_line(scan_folder) -> None:
    truth = scan_folder / "scan.labels"
    result = CliRunner().invoke(
        app,
        [
            "label",
            str(scan_folder / "scan.txt"),
            "--labels",
            str(truth),
            "--port",
            str(_free_port()),
        ],
    )
    assert result.exit_code == 2, result.output
    assert "pass --overwrite" in result.output and "Traceback" not in result.output
    outside = CliRunner().invoke(app, ["view", str(scan_folder / "scan.txt"), "--host", "0.0.0.0"])
    assert outside.exit_code == 2 and "loopback" in outside.output


def test_cli_label_and_view_on_a_busy_port_are_one_line_before_any_work(scan_folder) -> None:
    before = _listing(scan_folder)
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = str(holder.getsockname()[1])
        for command in (["label"], ["view"]):
            result = CliRunner().invoke(
                app, [*command, str(scan_folder / "scan.txt"), "--port", port]
            )
            assert result.exit_code == 2, result.output
            lines = [line for line in result.output.splitlines() if line.strip()]
            assert len(lines) == 1 and f"port {port} on 127.0.0.1: cannot listen" in lines[0]
            assert "pass --port" in lines[0]
    assert _listing(scan_folder) == before  # refused before planning or caching anything


def test_cli_label_says_where_labels_go_and_prints_the_secret_once(
    scan_folder, labelling_cache_dir
) -> None:
    import httpx

    port = _free_port()
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(sys.path),
        CACHE_DIR_ENV: str(labelling_cache_dir),
        "COLUMNS": "200",
    }
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "semantic3d",
            "label",
            str(scan_folder / "scan.txt"),
            "--port",
            str(port),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
    )
    lines: list[str] = []
    try:
        assert process.stdout is not None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = process.stdout.readline()
            lines.append(line)
            if "?token=" in line or not line:
                break
        url = next(line.strip() for line in lines if "?token=" in line)
        assert any(
            "starting from" in line
            and "scan.labels (read-only)" in line
            and "scan.edit.labels" in line
            for line in lines
        ), lines
        base, token = url.split("/?token=")
        assert base == f"http://127.0.0.1:{port}" and len(token) >= 32
        for _ in range(100):
            try:
                answer = httpx.get(f"{base}/api/summary", headers={"X-Semantic3D-Token": token})
                break
            except httpx.ConnectError:
                time.sleep(0.1)
        assert answer.status_code == 200
        assert answer.json()["labels_path"].endswith("scan.edit.labels")
        assert httpx.get(f"{base}/api/summary").status_code == 403
    finally:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(20)
    assert sum("?token=" in line for line in lines) == 1
