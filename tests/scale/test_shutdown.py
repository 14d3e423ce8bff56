"""A command on local Dask workers prints its own lines only: Dask's log lines need
``--verbose``, and the cluster's shutdown prints nothing."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_a_local_cluster_starts_and_stops_quietly(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), COLUMNS="200")
    command = ["simulate", "--points", "20000", "--stations", "2", "--out", str(tmp_path)]
    done = subprocess.run(
        [sys.executable, "-m", "semantic3d", *command, "--workers", "2"],
        capture_output=True,
        text=True,
        env=env,
        stdin=subprocess.DEVNULL,
        timeout=300,
        check=True,
    )
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    noise = [line for line in lines if not line.startswith(("Dask: ", "scanning"))]
    assert noise == [], done.stderr
    assert any(line.startswith("Dask: 2 local worker processes") for line in lines)
