"""Reference results: published rows shown on the leaderboards, each with its source.

They come from ``reference_results.toml`` (versioned): every row of the semantic3D.net
paper's Tables 1 and 2, and later published records, each naming the document its values
were read from. They are shown on the boards of ``semantic-8`` and ``reduced-8`` only,
tagged (:data:`TAG_PAPER_BASELINE`, :data:`TAG_PUBLISHED`), sorted in with the
participants so they can be compared, but never given a rank. A value the file leaves out
is unknown and shown as an empty cell.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from semantic3d.core.classes import CLASSES, class_by_name
from semantic3d.core.errors import DataFormatError

REFERENCE_RESULTS_PATH = Path(__file__).with_name("reference_results.toml")

TAG_PAPER_BASELINE = "paper-baseline"
"""A baseline of the semantic3D.net paper, as its tables print it."""
TAG_PUBLISHED = "published"
"""A result published elsewhere and not evaluated by this server."""
TAG_VERIFIED = "verified"
"""A participant's submission, evaluated by this server on the hidden ground truth."""
TAGS = (TAG_VERIFIED, TAG_PAPER_BASELINE, TAG_PUBLISHED)
TAG_LABELS = {
    TAG_VERIFIED: "verified submission",
    TAG_PAPER_BASELINE: "paper baseline",
    TAG_PUBLISHED: "published, not verified here",
}
"""How the pages name each tag (filters, notes, method pages)."""
TAG_SHORT_LABELS = {
    TAG_VERIFIED: "verified",
    TAG_PAPER_BASELINE: "paper baseline",
    TAG_PUBLISHED: "published",
}
"""How a board's tag column names each tag (the full label is its tooltip)."""

_TOP_KEYS = frozenset({"version", "benchmark_source", "sources", "results"})
_SOURCE_KEYS = frozenset({"citation", "url", "label", "year"})
_RESULT_KEYS = frozenset(
    {
        "challenge",
        "method",
        "tag",
        "source",
        "table",
        "mean_iou",
        "overall_accuracy",
        "iou",
        "iou_notes",
        "runtime_s",
        "hardware",
        "paper_url",
        "code_url",
        "description",
        "note",
    }
)
_CHALLENGES = ("semantic-8", "reduced-8")
_REFERENCE_TAGS = (TAG_PAPER_BASELINE, TAG_PUBLISHED)
# Three printed decimals: a mean of rounded values may differ by half a unit and a bit.
_MEAN_TOLERANCE = 0.0006


@dataclass(frozen=True, slots=True)
class ReferenceSource:
    """A publication reference values were read from."""

    key: str
    citation: str
    url: str
    label: str
    year: int


@dataclass(frozen=True, slots=True)
class ReferenceResult:
    """One published row: scores as fractions, ``None`` where the value is not known.

    ``key`` names the row in URLs (unique per challenge); ``iou_notes`` holds, per class,
    the footnote the source attaches to that cell ("" for none); ``table`` says where in
    the source the row is printed.
    """

    key: str
    challenge: str
    method: str
    tag: str
    mean_iou: float | None
    overall_accuracy: float | None
    iou: tuple[float | None, ...]  # per class, in class order (label values 1..8)
    iou_notes: tuple[str, ...]
    runtime_s: float | None
    hardware: str | None
    paper_url: str
    code_url: str
    description: str
    note: str
    table: str
    source: ReferenceSource


@dataclass(frozen=True, slots=True)
class ReferenceResults:
    """Every reference result of one file, its sources and the file's version."""

    version: int
    sources: tuple[ReferenceSource, ...]
    benchmark_source: ReferenceSource
    results: tuple[ReferenceResult, ...]

    def for_challenge(self, kind: str) -> tuple[ReferenceResult, ...]:
        """The rows of challenge kind ``kind`` (none for custom challenges)."""
        return tuple(result for result in self.results if result.challenge == kind)

    def find(self, kind: str, key: str) -> ReferenceResult | None:
        """The row of challenge kind ``kind`` called ``key`` in URLs, if any."""
        for result in self.for_challenge(kind):
            if result.key == key:
                return result
        return None


def reference_key(method: str) -> str:
    """The name of a row in URLs: its method, lower case, runs of other characters as ``-``.

    >>> reference_key("TMLC-MSR"), reference_key("RandLA-Net"), reference_key("SCF Net (v2)")
    ('tmlc-msr', 'randla-net', 'scf-net-v2')
    """
    return re.sub(r"[^a-z0-9]+", "-", method.lower()).strip("-")


def read_reference_results(path: Path = REFERENCE_RESULTS_PATH) -> ReferenceResults:
    """Read and check a reference-results file (see ``reference_results.toml``).

    Raises:
        DataFormatError: unknown keys, unknown challenges, tags, sources or classes,
            values outside 0..1, two rows of one challenge with the same key, or per-class
            IoU whose mean contradicts the stated mean IoU.
    """
    with path.open("rb") as handle:
        data = tomllib.load(handle)
    where = path.name
    _reject_unknown(data, _TOP_KEYS, where)
    version = data.get("version")
    if not isinstance(version, int):
        raise DataFormatError(f"{where}: version: expected an integer, found {version!r}")
    raw_sources = data.get("sources")
    if not isinstance(raw_sources, dict) or not raw_sources:
        raise DataFormatError(
            f"{where}: expected [sources.NAME] tables (citation, url, label, year)"
        )
    sources = {
        key: _source(key, raw, f"{where}: [sources.{key}]") for key, raw in raw_sources.items()
    }
    benchmark = data.get("benchmark_source")
    if benchmark not in sources:
        raise DataFormatError(
            f"{where}: benchmark_source: expected one of {', '.join(sources)}, found {benchmark!r}"
        )
    results = tuple(
        _result(raw, sources, f"{where}: results[{index}]")
        for index, raw in enumerate(data.get("results", []))
    )
    seen: set[tuple[str, str]] = set()
    for result in results:
        if (result.challenge, result.key) in seen:
            raise DataFormatError(
                f"{where}: {result.method}: two rows of {result.challenge} named {result.key!r}"
            )
        seen.add((result.challenge, result.key))
    return ReferenceResults(
        version=version,
        sources=tuple(sources.values()),
        benchmark_source=sources[str(benchmark)],
        results=results,
    )


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


def _text(raw: dict[str, Any], key: str, where: str) -> str:
    value = raw.get(key, "")
    if not isinstance(value, str):
        raise DataFormatError(f"{where}: {key}: expected text, found {value!r}")
    return " ".join(value.split())


def _link(raw: dict[str, Any], key: str, where: str) -> str:
    value = _text(raw, key, where)
    if value and not value.startswith("https://"):
        raise DataFormatError(f"{where}: {key}: expected an https:// address, found {value!r}")
    return value


def _source(key: str, raw: Any, where: str) -> ReferenceSource:
    if not isinstance(raw, dict):
        raise DataFormatError(f"{where}: expected a table, found {raw!r}")
    _reject_unknown(raw, _SOURCE_KEYS, where)
    year = raw.get("year")
    source = ReferenceSource(
        key=key,
        citation=_text(raw, "citation", where),
        url=_link(raw, "url", where),
        label=_text(raw, "label", where),
        year=year if isinstance(year, int) and not isinstance(year, bool) else 0,
    )
    if not (source.citation and source.url and source.label and source.year > 0):
        raise DataFormatError(f"{where}: expected a citation, an https url, a label and a year")
    return source


def _fraction(raw: dict[str, Any], key: str, where: str) -> float | None:
    value = raw.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DataFormatError(f"{where}: {key}: expected a number 0..1, found {value!r}")
    if not 0.0 <= float(value) <= 1.0:
        raise DataFormatError(f"{where}: {key}: expected a fraction 0..1, found {value}")
    return float(value)


def _per_class(raw: dict[str, Any], key: str, where: str) -> dict[int, Any]:
    table = raw.get(key, {})
    if not isinstance(table, dict):
        raise DataFormatError(f"{where}: {key}: expected a table of class name = value")
    by_value: dict[int, Any] = {}
    for name in table:
        try:
            cls = class_by_name(name)
        except ValueError as exc:
            raise DataFormatError(f"{where}: {key}: {exc}") from None
        by_value[cls.value] = name
    return by_value


def _result(raw: Any, sources: dict[str, ReferenceSource], where: str) -> ReferenceResult:
    if not isinstance(raw, dict):
        raise DataFormatError(f"{where}: expected a table, found {raw!r}")
    _reject_unknown(raw, _RESULT_KEYS, where)
    challenge = raw.get("challenge")
    if challenge not in _CHALLENGES:
        raise DataFormatError(
            f"{where}: challenge: expected one of {', '.join(_CHALLENGES)}, found {challenge!r}"
        )
    method = _text(raw, "method", where)
    if not method:
        raise DataFormatError(f"{where}: method: expected a name")
    where = f"{where} ({method})"
    tag = raw.get("tag")
    if tag not in _REFERENCE_TAGS:
        raise DataFormatError(
            f"{where}: tag: expected one of {', '.join(_REFERENCE_TAGS)}, found {tag!r}"
        )
    source_key = raw.get("source")
    if source_key not in sources:
        raise DataFormatError(
            f"{where}: source: expected one of {', '.join(sources)}, found {source_key!r}"
        )
    iou_names = _per_class(raw, "iou", where)
    iou = tuple(
        _fraction(raw["iou"], iou_names[cls.value], f"{where}: iou")
        if cls.value in iou_names
        else None
        for cls in CLASSES
    )
    note_names = _per_class(raw, "iou_notes", where)
    iou_notes = tuple(
        _text(raw["iou_notes"], note_names[cls.value], f"{where}: iou_notes")
        if cls.value in note_names
        else ""
        for cls in CLASSES
    )
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
    hardware = _text(raw, "hardware", where)
    return ReferenceResult(
        key=reference_key(method),
        challenge=str(challenge),
        method=method,
        tag=str(tag),
        mean_iou=mean_iou,
        overall_accuracy=_fraction(raw, "overall_accuracy", where),
        iou=iou,
        iou_notes=iou_notes,
        runtime_s=None if runtime is None else float(runtime),
        hardware=hardware or None,
        paper_url=_link(raw, "paper_url", where),
        code_url=_link(raw, "code_url", where),
        description=_text(raw, "description", where),
        note=_text(raw, "note", where),
        table=_text(raw, "table", where),
        source=sources[str(source_key)],
    )
