"""What every ``semantic3d baseline <name>`` command shares: options, choices, the scans a
``predict`` labels and where it writes, and the summary it prints.

Each baseline's command module (``baseline.py`` for the covariance baseline,
``baseline_cnn.py``, ``baseline_image.py``, ...) imports these; none imports another
baseline's module. Nothing heavy is imported here (the app is built from these modules at
start-up).
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import escape, fail, plural

if TYPE_CHECKING:
    from semantic3d.baselines.common.run import PredictionRunSet
    from semantic3d.baselines.common.submission import ScanToLabel

__all__ = [
    "CHECKPOINT_SUFFIX",
    "DEFAULT_PREDICTIONS",
    "OVERWRITE_HELP",
    "SCANS_HELP",
    "ChallengeChoice",
    "DeviceChoice",
    "challenge_option",
    "data_option",
    "out_option",
    "print_runs",
    "scan_argument",
    "scan_names",
    "scans_and_target",
]

SCANS_HELP = "Scan names (NAME of NAME.txt) to use, repeatable or comma-separated; default all."
OVERWRITE_HELP = "Replace outputs that already exist (refused otherwise)."

#: Where ``predict`` writes when no --out is given (relative to the working directory).
DEFAULT_PREDICTIONS = Path("predictions")

CHECKPOINT_SUFFIX = ".checkpoint"
"""The checkpoint of ``train --out MODEL`` is ``MODEL.checkpoint``."""


class ChallengeChoice(StrEnum):
    """Test challenges whose scans ``predict --data`` can label under official names."""

    SEMANTIC_8 = "semantic-8"
    REDUCED_8 = "reduced-8"


class DeviceChoice(StrEnum):
    """Where a network runs."""

    CPU = "cpu"
    CUDA = "cuda"


def scan_argument() -> Any:
    """``predict``'s optional SCAN argument (one scan; or ``--data``)."""
    return typer.Argument(None, help="One scan to label (any format); or use --data.")


def data_option() -> Any:
    """``predict``'s ``--data DIR``: every scan of a folder."""
    return typer.Option(
        None, "--data", file_okay=False, help="Label every scan of this folder (NAME.txt)."
    )


def out_option() -> Any:
    """``predict``'s ``--out``: a folder, a zip, or for one scan a ``.labels`` file."""
    return typer.Option(
        None,
        "--out",
        help="A folder (default ./predictions), a zip archive ready for `submit` (ends in "
        ".zip) or, for one scan, a .labels file.",
    )


def challenge_option() -> Any:
    """``predict``'s ``--challenge``: the challenge's scans under their official names."""
    return typer.Option(
        None,
        "--challenge",
        "-c",
        help="With --data: label the challenge's scans under their official submission "
        "names (default: every NAME.txt, as NAME.labels).",
    )


def scan_names(scans: list[str]) -> list[str]:
    """The names of repeatable, comma-separated ``--scans`` options."""
    return [name.strip() for item in scans for name in item.split(",") if name.strip()]


def scans_and_target(
    scan: Path | None, data: Path | None, out: Path | None, challenge: ChallengeChoice | None
) -> tuple[tuple[ScanToLabel, ...], Path]:
    """What ``predict`` labels and the folder or zip it writes to."""
    from semantic3d.baselines.common.submission import ScanToLabel, find_scans_to_label

    target = out if out is not None else DEFAULT_PREDICTIONS
    if data is not None:
        if scan is not None:
            raise fail("expected one SCAN argument or --data DIR, found both")
        if target.suffix == ".labels":
            raise fail(f"{target}: with --data, --out is a folder or a .zip archive")
        challenge_name = None if challenge is None else challenge.value
        return find_scans_to_label(data, challenge=challenge_name), target
    if scan is None:
        raise fail("expected one SCAN argument or --data DIR, found neither")
    if challenge is not None:
        raise fail("--challenge applies to --data DIR (a folder of the challenge's scans)")
    if not scan.is_file():
        raise fail(f"{scan}: expected a scan file (x y z intensity r g b lines), found none")
    if target.suffix == ".labels":  # one scan into a named labels file
        return (ScanToLabel(scan.stem, scan, target.name),), target.parent
    return (ScanToLabel(scan.stem, scan, scan.stem + ".labels"),), target


def print_runs(result: PredictionRunSet, *, zipped: bool, challenge: str | None) -> None:
    """One line per labelled scan, a total for many, and the ``submit`` line for a zip."""
    for run in result.runs:
        ui.console.print(
            f"{escape(Path(run.scan).name)}: {plural(run.n_points, 'point')} labelled in "
            f"{run.runtime_s:.1f} s ({run.points_per_second:,.0f} points/s"
            f"{', tiled' if run.tiled else ''}) -> {escape(run.labels_path)}",
            highlight=False,
            soft_wrap=True,
        )
    if len(result.runs) > 1 or zipped:
        ui.console.print(
            f"{plural(len(result.runs), 'scan')}, {plural(result.n_points, 'point')} in "
            f"{result.runtime_s:.1f} s -> {escape(result.out)}",
            highlight=False,
            soft_wrap=True,
        )
    if zipped:
        hardware = result.runs[0].hardware.describe() if result.runs else ""
        ui.console.print(
            "submit it with: semantic3d submit --server URL --token TOKEN "
            f"--challenge {challenge or 'NAME'} --method NAME --runtime-s {result.runtime_s:.0f} "
            f"--hardware {escape(repr(hardware))} {escape(result.out)}",
            highlight=False,
            soft_wrap=True,
        )
