"""Prediction over whole scans in bounded memory, with the run's time and hardware.

A scan streams through :func:`~semantic3d.features.scan.iter_scan_features` (whole in
memory when small, tile by tile otherwise). Each feature row is classified once: in voxel
mode a row is a level-0 voxel and its label goes to every point inside it (all of them
have the same features, so this *is* per-point prediction, not an approximation); in
per-point mode every point has its own row. Labels land in a memory-mapped scratch file
indexed by point, then stream to the ``.labels`` file in the input's point order.
A JSON sidecar records the run time and hardware, as the benchmark asks of submissions.
"""

from __future__ import annotations

import contextlib
import json
import mmap
import os
import platform
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.core.pointcloud import PointCloud
from semantic3d.features.multiscale import compute_multiscale_features
from semantic3d.features.scan import iter_scan_features
from semantic3d.io.ascii import iter_ascii_points
from semantic3d.io.labels import write_labels

Progress = Callable[[int, int], None]
"""``progress(points_labelled, n_points_or_0_while_unknown)``."""


@dataclass(frozen=True, slots=True)
class HardwareInfo:
    """The machine a run used."""

    cpu_model: str
    physical_cores: int
    logical_cores: int
    ram_bytes: int
    platform: str
    python: str

    def describe(self) -> str:
        """One line, e.g. ``AMD EPYC, 2 cores / 2 threads, 23.5 GiB RAM, Linux``."""
        return (
            f"{self.cpu_model}, {self.physical_cores} cores / {self.logical_cores} threads, "
            f"{self.ram_bytes / 2**30:.1f} GiB RAM, {self.platform}"
        )


@dataclass(frozen=True, slots=True)
class PredictionRun:
    """What a prediction run produced and cost.

    Attributes:
        scan: the input points file.
        labels_path: the written ``.labels`` file.
        n_points: points labelled.
        runtime_s: wall time from opening the scan to the last label written (T).
        tiled: whether the scan was processed tile by tile.
        hardware: the machine.
        package_version: semantic3d version.
        training_scans: the model's training scans.
    """

    scan: str
    labels_path: str
    n_points: int
    runtime_s: float
    tiled: bool
    hardware: HardwareInfo
    package_version: str
    training_scans: tuple[str, ...]

    @property
    def points_per_second(self) -> float:
        """Throughput of the run."""
        return self.n_points / self.runtime_s if self.runtime_s > 0 else float("inf")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (the sidecar's content)."""
        data = asdict(self)
        data["training_scans"] = list(self.training_scans)
        data["points_per_second"] = self.points_per_second
        return data


def describe_hardware() -> HardwareInfo:
    """CPU model, cores and RAM of this machine (psutil / platform)."""
    return HardwareInfo(
        cpu_model=_cpu_model(),
        physical_cores=psutil.cpu_count(logical=False) or 0,
        logical_cores=psutil.cpu_count(logical=True) or 0,
        ram_bytes=int(psutil.virtual_memory().total),
        platform=f"{platform.system()} {platform.release()}",
        python=platform.python_version(),
    )


def predict_cloud(model: CovarianceModel, cloud: PointCloud) -> NDArray[np.uint8]:
    """Label values of every point of an in-memory cloud."""
    table = compute_multiscale_features(cloud, config=model.config.features)
    return model.predict_rows(table.values)[table.point_row]


def predict_scan(
    model: CovarianceModel,
    points_path: str | Path,
    *,
    out_path: str | Path | None = None,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
) -> PredictionRun:
    """Label every point of an ASCII scan; write ``.labels`` and a ``.labels.json`` sidecar.

    Args:
        model: a trained model.
        points_path: the scan (``x y z intensity r g b`` lines).
        out_path: labels file (default ``points_path`` with suffix ``.labels``).
        workdir: scratch folder for tiles and the label buffer (default a temporary one).
        progress: called with points labelled so far.
    """
    started = time.perf_counter()
    points_path = Path(points_path)
    out = Path(out_path) if out_path is not None else points_path.with_suffix(".labels")
    prediction = model.config.prediction
    with tempfile.TemporaryDirectory(prefix="s3d-predict-", dir=workdir) as scratch:
        scratch_dir = Path(scratch)
        buffer = _LabelBuffer(scratch_dir / "labels.u8")
        done = 0
        tiled = False
        try:
            for block in iter_scan_features(
                iter_ascii_points(points_path, chunk_size=prediction.chunk_size),
                config=model.config.features,
                max_points_in_memory=prediction.max_points_in_memory,
                tile_size_m=prediction.tile_size_m,
                workdir=scratch_dir / "tiles",
            ):
                tiled = block.tiled
                row_labels = model.predict_rows(block.table.values)
                buffer.put(
                    block.point_indices, row_labels[block.table.point_row], block.n_scan_points
                )
                done += block.point_indices.size
                if progress is not None:
                    progress(done, block.n_scan_points)
            out.parent.mkdir(parents=True, exist_ok=True)
            written = write_labels(out, buffer.iter_chunks(prediction.chunk_size))
        finally:
            buffer.close()
    run = PredictionRun(
        scan=str(points_path),
        labels_path=str(out),
        n_points=written,
        runtime_s=time.perf_counter() - started,
        tiled=tiled,
        hardware=describe_hardware(),
        package_version=__version__,
        training_scans=model.training_scans,
    )
    sidecar = out.with_name(out.name + ".json")
    sidecar.write_text(json.dumps(run.to_dict(), indent=2) + "\n")
    return run


class _LabelBuffer:
    """A uint8 label per point in a memory-mapped file; resident pages are dropped as
    blocks are written and read, so memory does not grow with the scan."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = path.open("w+b")
        self._map: mmap.mmap | None = None
        self.n_points = 0

    def _ensure(self, n_points: int) -> NDArray[np.uint8]:
        if self._map is None:
            self.n_points = n_points
            os.ftruncate(self._file.fileno(), max(n_points, 1))
            self._map = mmap.mmap(self._file.fileno(), max(n_points, 1))
        return np.frombuffer(self._map, np.uint8, count=self.n_points)

    def put(self, indices: NDArray[np.int64], labels: NDArray[np.uint8], n_points: int) -> None:
        view = self._ensure(n_points)
        view[indices] = labels
        del view
        self._release()

    def iter_chunks(self, chunk_size: int) -> Iterator[NDArray[np.uint8]]:
        view = self._ensure(0)
        for begin in range(0, self.n_points, chunk_size):
            yield view[begin : begin + chunk_size].copy()
            self._release()
        del view

    def _release(self) -> None:
        if self._map is not None:
            self._map.flush()
            self._map.madvise(mmap.MADV_DONTNEED)

    def close(self) -> None:
        if self._map is not None:
            with contextlib.suppress(BufferError):  # a live view: the file goes with the folder
                self._map.close()
        self._file.close()


def _cpu_model() -> str:
    try:
        with Path("/proc/cpuinfo").open() as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"
