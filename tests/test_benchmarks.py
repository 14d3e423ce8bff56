"""The benchmarks run end to end on tiny scans. The scaling one: each path against its
peer and floor, its counts checked against the peer's, the table written where it is told
(a device run that fails halfway costs what a test run costs nothing). The cylinder one:
its two kernels agree bit for bit and the peer is measured."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, *args: str) -> str:
    """A benchmark script run to its end in a fresh interpreter; its standard output."""
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *args],
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        env={**os.environ, "PYTHONPATH": str(ROOT / "src")},
        timeout=500,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip()


@pytest.mark.slow
def test_the_scaling_benchmark_measures_each_path_beside_its_peer_and_floor(
    tmp_path: Path,
) -> None:
    out = tmp_path / "out"
    _run(
        "bench_scaling.py",
        *("--points", "20000", "--threads", "1", "--repeat", "1", "--min-seconds", "0"),
        *("--paths", "evaluate", "read_labels", "simulate"),
        *("--out", str(out), "--workdir", str(tmp_path)),
    )
    report = json.loads((out / "bench_scaling.json").read_text())
    rows = {row["path"]: row for row in report["rows"]}
    assert set(rows) == {"evaluate", "read_labels", "simulate"}
    for row in rows.values():
        assert row["threads"] == 1 and row["rate"] > 0 and row["peak_bytes"] > 0
    assert rows["evaluate"]["agrees_with_peer"] is True  # the same matrix as pyarrow + numpy
    for path in ("evaluate", "read_labels"):
        assert rows[path]["peer_rate"] > 0 and rows[path]["floor_rate"] > 0
        assert rows[path]["peer_peak_bytes"] > 0
    assert len(rows["simulate"]["digest"]) == 12
    assert not list(tmp_path.glob("bench-scaling-*"))  # its scratch folder removed


def test_the_cylinder_benchmark_checks_its_kernels_agree_and_measures_the_peer() -> None:
    lines = _run("bench_cylinders.py", "--points", "30000", "--peer-queries", "300").splitlines()
    assert "the two kernels equal bit for bit" in lines[0]
    names = [line.split("  ")[0] for line in lines[2:]]
    assert names == ["cylinder_below alone", "four columns", "scipy cKDTree 2-D"]
