"""A simulation writes the same bytes on any number of threads (the writer overlaps the
next block's casting from six threads on)."""

from __future__ import annotations

from pathlib import Path

from semantic3d.core.threads import thread_limit
from semantic3d.datasets.simulator import simulate


def test_same_bytes_on_one_and_eight_threads(tmp_path: Path) -> None:
    outputs = []
    for n_threads in (1, 8):
        with thread_limit(n_threads):
            result = simulate(
                "street", out=tmp_path / str(n_threads), n_points=40_000, chunk_size=9_000
            )
        scan = result.scans[0]
        outputs.append((scan.points_path.read_bytes(), scan.labels_path.read_bytes()))
    assert outputs[0] == outputs[1]
