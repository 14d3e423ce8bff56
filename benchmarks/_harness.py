"""Tiny harness shared by the benchmark scripts: run a contender in a fresh process and
report its wall time and peak resident memory, so one contender's memory does not hide
another's."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"


@dataclass(frozen=True, slots=True)
class Measurement:
    name: str
    items: int
    seconds: float
    peak_rss_mb: float

    @property
    def rate(self) -> float:
        return self.items / self.seconds


def peak_rss_mb() -> float:
    """This process's peak resident memory. Linux's ``VmHWM`` where there is one: the
    ``ru_maxrss`` of a started child also holds the resident size of the parent that
    forked it (kept across ``exec``), so a large parent showed in every child."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1 << 20) if sys.platform == "darwin" else peak / 1024


def measure_here(name: str, run: Callable[[], int]) -> Measurement:
    """Time ``run`` (which returns the number of items it processed) in this process."""
    start = time.perf_counter()
    items = run()
    seconds = time.perf_counter() - start
    return Measurement(name, items, seconds, peak_rss_mb())


def measure_in_child(script: Path, name: str, *args: str) -> Measurement:
    """Run ``script --child NAME ARGS...`` in a fresh interpreter; it prints a JSON measurement."""
    result = subprocess.run(
        [sys.executable, str(script), "--child", name, *args],
        check=True,
        capture_output=True,
        text=True,
    )
    data = json.loads(result.stdout.strip().splitlines()[-1])
    return Measurement(**data)


def emit(measurement: Measurement) -> None:
    """Print a measurement as the child's last stdout line."""
    print(
        json.dumps(
            {
                "name": measurement.name,
                "items": measurement.items,
                "seconds": measurement.seconds,
                "peak_rss_mb": measurement.peak_rss_mb,
            }
        )
    )


def table(title: str, unit: str, rows: list[Measurement], baseline: str) -> str:
    """A plain-text table with rates and the ratio to ``baseline``."""
    reference = next(r for r in rows if r.name == baseline)
    lines = [
        title,
        f"{'contender':<34} {'M ' + unit + '/s':>10} {'x ' + baseline:>16} {'seconds':>9} {'peak RSS MB':>12}",
    ]
    for row in rows:
        lines.append(
            f"{row.name:<34} {row.rate / 1e6:>10.1f} {row.rate / reference.rate:>16.2f} "
            f"{row.seconds:>9.2f} {row.peak_rss_mb:>12.0f}"
        )
    return "\n".join(lines)
