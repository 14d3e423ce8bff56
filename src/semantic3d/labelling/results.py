"""What an operation reports, and the limits its parameters must respect."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from semantic3d.core.classes import N_CLASSES
from semantic3d.labelling.errors import OperationError

__all__ = ["MAX_RADIUS_M", "MAX_SEEDS", "MAX_TOLERANCE_M", "OperationResult"]

MAX_TOLERANCE_M = 100.0
"""Largest fit tolerance accepted (metres)."""
MAX_RADIUS_M = 100_000.0
"""Largest candidate radius of a fit accepted (metres)."""
MAX_SEEDS = 1000


def _finite(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else value


@dataclass(frozen=True, slots=True)
class OperationResult:
    """What an operation did."""

    operation: str
    entry_id: int | None
    n_working: int
    n_changed_labels: int
    n_working_changed: int
    model: dict[str, Any] | None = None
    n_inliers: int | None = None
    rms_m: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "operation": self.operation,
            "entry_id": self.entry_id,
            "n_working": self.n_working,
            "n_changed_labels": self.n_changed_labels,
            "n_working_changed": self.n_working_changed,
            "model": self.model,
            "n_inliers": self.n_inliers,
            "rms_m": _finite(self.rms_m),
        }


def _check_distance(name: str, value: float, maximum: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or not (math.isfinite(number) and 0 < number <= maximum):
        raise OperationError(
            f"{name}: expected a finite distance in metres, 0 < {name} <= {maximum:g}, "
            f"found {value!r}"
        )
    return number


def _layer(value: int) -> int:
    if isinstance(value, bool) or int(value) != value or not 0 <= int(value) <= N_CLASSES:
        raise OperationError(f"layer: expected a label value in 0..{N_CLASSES}, found {value!r}")
    return int(value)
