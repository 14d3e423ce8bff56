"""``EvaluationResult``: what evaluating a submission produces, and its JSON form.

The benchmark server stores :meth:`EvaluationResult.to_dict` as JSON and shows
:meth:`EvaluationResult.to_public_dict` (no per-scan scores: they would leak the test
labels scan by scan). Scores are recomputed from the stored confusion matrices when a
result is loaded, so the matrix is the single source of truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.core.classes import CLASSES
from semantic3d.core.errors import DataFormatError
from semantic3d.metrics.scores import Scores, compute_scores

RESULT_FORMAT = "semantic3d.evaluation-result/1"
"""Tag of the JSON layout written by :meth:`EvaluationResult.to_dict`."""


@dataclass(frozen=True, slots=True)
class MethodInfo:
    """The method a submission comes from: its name and run time T as the paper's tables
    list them, and what the paper asks participants to state besides (hardware, Section 5).

    Attributes:
        name: method name shown in tables.
        runtime_s: total processing time in seconds (the tables' ``T``), if reported.
        hardware: what it ran on (free text), if reported.
    """

    name: str
    runtime_s: float | None = None
    hardware: str | None = None
    description: str = ""
    paper_url: str = ""
    code_url: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        return {
            "name": self.name,
            "runtime_s": self.runtime_s,
            "hardware": self.hardware,
            "description": self.description,
            "paper_url": self.paper_url,
            "code_url": self.code_url,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MethodInfo:
        """Inverse of :meth:`to_dict`."""
        runtime = data.get("runtime_s")
        return cls(
            name=str(data["name"]),
            runtime_s=None if runtime is None else float(runtime),
            hardware=data.get("hardware"),
            description=str(data.get("description", "")),
            paper_url=str(data.get("paper_url", "")),
            code_url=str(data.get("code_url", "")),
        )


@dataclass(frozen=True, slots=True)
class ScanResult:
    """Scores of one scan (private: never shown on a public leaderboard)."""

    name: str
    submission_name: str
    confusion: NDArray[np.int64]
    scores: Scores

    @property
    def n_points(self) -> int:
        """Labelled points of the scan that were scored."""
        return self.scores.n_points


@dataclass(frozen=True, slots=True)
class EvaluationResult:
    """The outcome of :func:`~semantic3d.evaluation.evaluate_submission`.

    Attributes:
        challenge: challenge name (``semantic-8``, ``reduced-8``, ``custom:...``).
        protocol_version: version of the protocol file the numbers follow.
        confusion: ``(8, 8)`` int64 counts over every scan, rows ground truth.
        scores: scores of ``confusion``.
        n_points: labelled points scored (ground truth 1..8).
        method: the method, when given.
        per_scan: scores per scan, private.
        software_version: version of this package that computed the result.
    """

    challenge: str
    protocol_version: str
    confusion: NDArray[np.int64]
    scores: Scores
    n_points: int
    method: MethodInfo | None = None
    per_scan: tuple[ScanResult, ...] = ()
    software_version: str = __version__

    @property
    def mean_iou(self) -> float:
        """Mean IoU over present classes (the leaderboard's ranking score)."""
        return self.scores.mean_iou

    @property
    def overall_accuracy(self) -> float:
        """Correct labelled points / labelled points."""
        return self.scores.overall_accuracy

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (NaN as null), per-scan scores included."""
        data = self.to_public_dict()
        data["per_scan"] = [
            {
                "name": scan.name,
                "submission_name": scan.submission_name,
                "confusion": scan.confusion.tolist(),
                "scores": scores_to_dict(scan.scores),
            }
            for scan in self.per_scan
        ]
        return data

    def to_public_dict(self) -> dict[str, Any]:
        """JSON-safe form without the per-scan scores."""
        return {
            "format": RESULT_FORMAT,
            "challenge": self.challenge,
            "protocol_version": self.protocol_version,
            "software_version": self.software_version,
            "method": None if self.method is None else self.method.to_dict(),
            "n_points": self.n_points,
            "classes": [cls.name for cls in CLASSES],
            "confusion": self.confusion.tolist(),
            "scores": scores_to_dict(self.scores),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EvaluationResult:
        """Inverse of :meth:`to_dict` (also accepts the public form, without per-scan)."""
        if data.get("format") != RESULT_FORMAT:
            raise DataFormatError(
                f"evaluation result: expected format {RESULT_FORMAT!r}, "
                f"found {data.get('format')!r}"
            )
        confusion = _matrix(data["confusion"], where="confusion")
        method = data.get("method")
        per_scan = tuple(
            ScanResult(
                name=str(scan["name"]),
                submission_name=str(scan["submission_name"]),
                confusion=(matrix := _matrix(scan["confusion"], where=f"scan {scan['name']}")),
                scores=compute_scores(matrix),
            )
            for scan in data.get("per_scan", [])
        )
        scores = compute_scores(confusion)
        return cls(
            challenge=str(data["challenge"]),
            protocol_version=str(data["protocol_version"]),
            confusion=confusion,
            scores=scores,
            n_points=scores.n_points,
            method=None if method is None else MethodInfo.from_dict(method),
            per_scan=per_scan,
            software_version=str(data.get("software_version", "")),
        )


def _matrix(rows: Any, *, where: str) -> NDArray[np.int64]:
    matrix = np.asarray(rows, dtype=np.int64)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise DataFormatError(f"evaluation result: {where}: expected a square matrix")
    return matrix


def _float_or_none(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def scores_to_dict(scores: Scores) -> dict[str, Any]:
    """JSON-safe form of :class:`Scores` (NaN as null), class-indexed lists."""
    return {
        "mean_iou": _float_or_none(scores.mean_iou),
        "overall_accuracy": _float_or_none(scores.overall_accuracy),
        "n_points": scores.n_points,
        "iou": [_float_or_none(v) for v in scores.iou],
        "precision": [_float_or_none(v) for v in scores.precision],
        "recall": [_float_or_none(v) for v in scores.recall],
        "f1": [_float_or_none(v) for v in scores.f1],
        "present": [bool(v) for v in scores.present],
        "absent": [CLASSES[i].name for i in scores.absent_indices if i < len(CLASSES)],
    }
