"""The record of a prediction run: what was labelled, how long it took (T), on which machine.

The benchmark asks every submission for its run time and hardware; each baseline writes
this record as JSON beside its ``.labels`` (``NAME.labels.json``), or for a zip
submission, in ``ARCHIVE.zip.json``.
"""

from __future__ import annotations

import platform
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import psutil

__all__ = ["HardwareInfo", "PredictionRun", "PredictionRunSet", "describe_hardware"]


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
        """JSON-safe dict (the run record's content)."""
        data = asdict(self)
        data["training_scans"] = list(self.training_scans)
        data["points_per_second"] = self.points_per_second
        return data


@dataclass(frozen=True, slots=True)
class PredictionRunSet:
    """What a run over many scans wrote: one run per scan, in order, and the output.

    Attributes:
        out: the folder or zip archive written.
        runs: each scan's run; for a zip, ``labels_path`` reads ``ARCHIVE.zip:NAME.labels``.
        runtime_s: wall time of the whole run (model already loaded).
    """

    out: str
    runs: tuple[PredictionRun, ...]
    runtime_s: float

    @property
    def n_points(self) -> int:
        """Points labelled over every scan."""
        return sum(run.n_points for run in self.runs)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (the content of ``ARCHIVE.zip.json``)."""
        return {
            "out": self.out,
            "n_points": self.n_points,
            "runtime_s": self.runtime_s,
            "hardware": asdict(self.runs[0].hardware) if self.runs else None,
            "scans": [run.to_dict() for run in self.runs],
        }


def _cpu_model() -> str:
    try:
        with Path("/proc/cpuinfo").open() as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"
