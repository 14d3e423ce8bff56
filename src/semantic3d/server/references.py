"""Reference results: the semantic3D.net paper's published rows, shown on the leaderboards.

They come from ``reference_results.toml`` (versioned, with its citation) and are shown
on the boards of ``semantic-8`` and ``reduced-8`` only, marked as references: sorted in
with the participants by mean IoU so they can be compared, but never given a rank. A
value the file leaves out is unknown and shown as an empty cell.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from semantic3d.core.classes import CLASSES, class_by_name
from semantic3d.core.errors import DataFormatError

REFERENCE_RESULTS_PATH = Path(__file__).with_name("reference_results.toml")

_TOP_KEYS = frozenset({"version", "source", "results"})
_SOURCE_KEYS = frozenset({"citation", "url", "label"})
_RESULT_KEYS = frozenset(
    {"challenge", "method", "mean_iou", "overall_accuracy", "iou", "runtime_s", "note"}
)
_CHALLENGES = ("semantic-8", "reduced-8")
# The paper prints three decimals: a mean of rounded values may differ by half a unit.
_MEAN_TOLERANCE = 0.0006


@dataclass(frozen=True, slots=True)
class ReferenceSource:
    """Where the reference results were published."""

    citation: str
    url: str
    label: str


@dataclass(frozen=True, slots=True)
class ReferenceResult:
    """One published row: scores as fractions, ``None`` where the value is not known."""

    challenge: str
    method: str
    mean_iou: float | None
    overall_accuracy: float | None
    iou: tuple[float | None, ...]  # per class, in class order (label values 1..8)
    runtime_s: float | None
    note: str
    source: ReferenceSource


@dataclass(frozen=True, slots=True)
class ReferenceResults:
    """Every reference result of one file and the file's version."""

    version: int
    source: ReferenceSource
    results: tuple[ReferenceResult, ...]

    def for_challenge(self, kind: str) -> tuple[ReferenceResult, ...]:
        """The rows of challenge kind ``kind`` (none for custom challenges)."""
        return tuple(result for result in self.results if result.challenge == kind)


def read_reference_results(path: Path = REFERENCE_RESULTS_PATH) -> ReferenceResults:
    """Read and check a reference-results file (see ``reference_results.toml``).

    Raises:
        DataFormatError: unknown keys, unknown challenges or classes, values outside 0..1,
            or per-class IoU whose mean contradicts the stated mean IoU.
    """
    with path.open("rb") as handle:
        data = tomllib.load(handle)
    where = path.name
    _reject_unknown(data, _TOP_KEYS, where)
    version = data.get("version")
    if not isinstance(version, int):
        raise DataFormatError(f"{where}: version: expected an integer, found {version!r}")
    raw_source = data.get("source")
    if not isinstance(raw_source, dict):
        raise DataFormatError(f"{where}: expected a [source] table with citation, url and label")
    _reject_unknown(raw_source, _SOURCE_KEYS, f"{where}: [source]")
    source = ReferenceSource(
        citation=" ".join(str(raw_source.get("citation", "")).split()),
        url=str(raw_source.get("url", "")),
        label=str(raw_source.get("label", "")),
    )
    if not (source.citation and source.url.startswith("https://") and source.label):
        raise DataFormatError(f"{where}: [source]: expected a citation, an https url and a label")
    results = tuple(
        _result(raw, source, f"{where}: results[{index}]")
        for index, raw in enumerate(data.get("results", []))
    )
    return ReferenceResults(version=version, source=source, results=results)


@cache
def reference_results() -> ReferenceResults:
    """The reference results shipped with the package (read once)."""
    return read_reference_results()


def _reject_unknown(table: dict[str, Any], known: frozenset[str], where: str) -> None:
    unknown = sorted(set(table) - known)
    if unknown:
        raise DataFormatError(
            f"{where}: unknown key(s) {', '.join(unknown)}: expected {', '.join(sorted(known))}"
        )


def _fraction(raw: dict[str, Any], key: str, where: str) -> float | None:
    value = raw.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DataFormatError(f"{where}: {key}: expected a number 0..1, found {value!r}")
    if not 0.0 <= float(value) <= 1.0:
        raise DataFormatError(f"{where}: {key}: expected a fraction 0..1, found {value}")
    return float(value)


def _result(raw: Any, source: ReferenceSource, where: str) -> ReferenceResult:
    if not isinstance(raw, dict):
        raise DataFormatError(f"{where}: expected a table, found {raw!r}")
    _reject_unknown(raw, _RESULT_KEYS, where)
    challenge = raw.get("challenge")
    if challenge not in _CHALLENGES:
        raise DataFormatError(
            f"{where}: challenge: expected one of {', '.join(_CHALLENGES)}, found {challenge!r}"
        )
    method = str(raw.get("method", "")).strip()
    if not method:
        raise DataFormatError(f"{where}: method: expected a name")
    where = f"{where} ({method})"
    raw_iou = raw.get("iou", {})
    if not isinstance(raw_iou, dict):
        raise DataFormatError(f"{where}: iou: expected a table of class name = IoU")
    by_value: dict[int, float | None] = {}
    for name in raw_iou:
        try:
            cls = class_by_name(name)
        except ValueError as exc:
            raise DataFormatError(f"{where}: iou: {exc}") from None
        by_value[cls.value] = _fraction(raw_iou, name, f"{where}: iou")
    iou = tuple(by_value.get(cls.value) for cls in CLASSES)
    mean_iou = _fraction(raw, "mean_iou", where)
    known = [value for value in iou if value is not None]
    if mean_iou is not None and len(known) == len(CLASSES):
        mean = math.fsum(known) / len(known)
        if abs(mean - mean_iou) > _MEAN_TOLERANCE:
            raise DataFormatError(
                f"{where}: mean_iou: the per-class IoU average {mean:.4f}, "
                f"found mean_iou = {mean_iou}"
            )
    runtime = raw.get("runtime_s")
    if runtime is not None and (
        isinstance(runtime, bool) or not isinstance(runtime, int | float) or runtime < 0
    ):
        raise DataFormatError(f"{where}: runtime_s: expected seconds >= 0, found {runtime!r}")
    return ReferenceResult(
        challenge=str(challenge),
        method=method,
        mean_iou=mean_iou,
        overall_accuracy=_fraction(raw, "overall_accuracy", where),
        iou=iou,
        runtime_s=None if runtime is None else float(runtime),
        note=str(raw.get("note", "")),
        source=source,
    )
