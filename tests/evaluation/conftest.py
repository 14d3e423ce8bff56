"""Helpers for evaluation tests: label files, submissions as folders and zips."""

from __future__ import annotations

import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pytest

from semantic3d.core import PointCloud


def labels_bytes(values: Sequence[int] | np.ndarray, *, crlf: bool = False) -> bytes:
    """``values`` as ``.labels`` text, one per line, with a final line end."""
    end = "\r\n" if crlf else "\n"
    return "".join(f"{int(v)}{end}" for v in values).encode()


def write_zip(
    path: Path,
    members: Mapping[str, bytes],
    *,
    compression: int = zipfile.ZIP_DEFLATED,
) -> Path:
    """A zip archive holding ``members`` (name -> bytes)."""
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


class Scans:
    """A tiny custom challenge: ground-truth files and a matching correct prediction."""

    def __init__(self, root: Path) -> None:
        rng = np.random.default_rng(3)
        self.gt_dir = root / "gt"
        self.gt_dir.mkdir()
        self.truth: dict[str, np.ndarray] = {}
        self.pred: dict[str, np.ndarray] = {}
        for name, n in (("alpha", 120), ("beta", 80)):
            truth = rng.integers(0, 9, n)
            pred = np.where(rng.random(n) < 0.7, np.maximum(truth, 1), rng.integers(1, 9, n))
            self.truth[f"{name}.labels"] = truth
            self.pred[f"{name}.labels"] = pred
            (self.gt_dir / f"{name}.labels").write_bytes(labels_bytes(truth))

    def pred_members(self) -> dict[str, bytes]:
        """The correct prediction as zip members."""
        return {name: labels_bytes(values) for name, values in self.pred.items()}

    def pred_folder(self, root: Path, members: Mapping[str, bytes] | None = None) -> Path:
        """Write ``members`` (default: the correct prediction) into a folder."""
        root.mkdir(parents=True, exist_ok=True)
        for name, data in (members or self.pred_members()).items():
            target = root / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        return root


@pytest.fixture
def scans(tmp_path: Path) -> Scans:
    """Two ground-truth scans (120 and 80 lines) and a valid prediction for them."""
    return Scans(tmp_path)


def _grid(columns: range, shift_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    i, j = np.meshgrid(np.array(columns), np.arange(100), indexing="ij")
    i, j = i.ravel(), j.ravel()
    xyz = np.column_stack([i * 0.1 + shift_m, j * 0.1 + shift_m, np.full(i.size, 2.0)])
    labels = np.where(i < 150, 1, 5).astype(np.uint8)
    return xyz, labels, np.column_stack([i, j])


def overlapping_scans() -> tuple[PointCloud, PointCloud]:
    """Scans A and B of ``test_agreement.py``: 0.1 m grids overlapping on x in [10, 20) m."""
    a_xyz, a_labels, a_ij = _grid(range(0, 200), 0.0)
    a_labels[(a_ij[:, 0] >= 120) & (a_ij[:, 0] < 125)] = 7
    b_xyz, b_labels, b_ij = _grid(range(100, 300), -0.01)
    b_labels[(b_ij[:, 0] < 110) & (b_ij[:, 1] < 10)] = 0
    b_labels[(b_ij[:, 0] >= 160) & (b_ij[:, 0] < 170)] = 3
    return (
        PointCloud.from_arrays(a_xyz, labels=a_labels),
        PointCloud.from_arrays(b_xyz, labels=b_labels),
    )
