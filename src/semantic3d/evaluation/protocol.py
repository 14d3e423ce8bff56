"""The versioned evaluation protocol: ``protocol_v<N>.toml`` shipped with the package.

The protocol file is the single written statement of the rules (classes, the ignore rule,
the matrix convention, the official challenges and their submission file names). Results
record the version they were computed under.
"""

from __future__ import annotations

import tomllib
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

from semantic3d.core.errors import DataFormatError

CURRENT_PROTOCOL_VERSION = "1"
"""The version :func:`load_protocol` reads by default."""


@dataclass(frozen=True, slots=True)
class ScanSpec:
    """One scan of an official challenge as the protocol file lists it."""

    name: str
    submission_name: str
    n_points: int | None


@dataclass(frozen=True, slots=True)
class ChallengeSpec:
    """An official challenge: its title and scans, in protocol order."""

    name: str
    title: str
    scans: tuple[ScanSpec, ...]


@dataclass(frozen=True, slots=True)
class Protocol:
    """The parsed protocol file.

    Attributes:
        version: protocol version (``"1"``).
        class_names: names of label values 1..n, in order.
        ignore_value: ground-truth label value dropped before scoring (0).
        prediction_min, prediction_max: the label values a submission may contain.
        convention: the written rules (matrix orientation, IoU, absent classes...).
        challenges: official challenges by name.
    """

    version: str
    benchmark: str
    class_names: tuple[str, ...]
    ignore_value: int
    prediction_min: int
    prediction_max: int
    convention: Mapping[str, str]
    challenges: Mapping[str, ChallengeSpec]

    @property
    def n_classes(self) -> int:
        """Number of classes scored."""
        return len(self.class_names)


def _check_keys(
    table: Mapping[str, Any], *, where: str, required: set[str], optional: Collection[str] = ()
) -> None:
    allowed = required | set(optional)
    unknown = sorted(set(table) - allowed)
    missing = sorted(required - set(table))
    if unknown:
        raise DataFormatError(f"{where}: unknown keys {unknown}, expected only {sorted(allowed)}")
    if missing:
        raise DataFormatError(f"{where}: missing keys {missing}")


def parse_protocol(data: Mapping[str, Any], *, source: str) -> Protocol:
    """Build a :class:`Protocol` from parsed TOML, rejecting unknown or missing keys."""
    _check_keys(
        data,
        where=source,
        required={"version", "benchmark", "labels", "convention"},
        optional={"challenges"},
    )
    labels = data["labels"]
    _check_keys(
        labels,
        where=f"{source}: [labels]",
        required={"ignore", "prediction_min", "prediction_max", "classes"},
    )
    challenges: dict[str, ChallengeSpec] = {}
    for name, table in data.get("challenges", {}).items():
        where = f"{source}: [challenges.{name}]"
        _check_keys(table, where=where, required={"title", "scans"})
        scans = []
        for number, scan in enumerate(table["scans"], start=1):
            _check_keys(
                scan,
                where=f"{where} scan {number}",
                required={"name", "submission"},
                optional={"n_points"},
            )
            scans.append(ScanSpec(scan["name"], scan["submission"], scan.get("n_points")))
        submission_names = [scan.submission_name for scan in scans]
        if len(set(submission_names)) != len(submission_names):
            raise DataFormatError(f"{where}: expected unique submission names, found duplicates")
        challenges[name] = ChallengeSpec(name, table["title"], tuple(scans))
    return Protocol(
        version=str(data["version"]),
        benchmark=str(data["benchmark"]),
        class_names=tuple(labels["classes"]),
        ignore_value=int(labels["ignore"]),
        prediction_min=int(labels["prediction_min"]),
        prediction_max=int(labels["prediction_max"]),
        convention=dict(data["convention"]),
        challenges=challenges,
    )


@cache
def load_protocol(version: str = CURRENT_PROTOCOL_VERSION) -> Protocol:
    """The protocol shipped with the package as ``protocol_v{version}.toml``."""
    file_name = f"protocol_v{version}.toml"
    resource = resources.files("semantic3d.evaluation").joinpath(file_name)
    if not resource.is_file():
        raise DataFormatError(
            f"evaluation protocol version {version!r}: expected a packaged {file_name}, "
            f"found none (current version: {CURRENT_PROTOCOL_VERSION})"
        )
    with resource.open("rb") as handle:
        data = tomllib.load(handle)
    return parse_protocol(data, source=file_name)
