"""What the training loops of the network baselines share: progress reports, the classes a
run trains on, balanced accuracy, and checkpoints written atomically.

Nothing here imports torch at module level; :func:`save_checkpoint` and
:func:`load_checkpoint` import it when called.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.scans import TrainingDataError
from semantic3d.core.classes import N_CLASSES, class_by_value
from semantic3d.core.errors import Semantic3DError, require

__all__ = [
    "CheckpointError",
    "TrainingProgress",
    "TrainingProgressCallback",
    "balanced_accuracy",
    "load_checkpoint",
    "save_checkpoint",
    "training_classes",
]


class CheckpointError(Semantic3DError, ValueError):
    """A checkpoint cannot resume this run (another configuration, other scans, corrupt)."""


@dataclass(frozen=True, slots=True)
class TrainingProgress:
    """Where a training run stands, after each mini-batch.

    Attributes:
        batch: mini-batches done.
        n_batches: mini-batches of the run.
        loss: mean loss of the current round's batches so far (NaN before the first).
        balanced_accuracy: mean per-class recall on the current round's batches so far.
        stage: what the run is doing: ``"train"``, or a preparation step named by the
            baseline (``"clouds"`` while a round's sub-clouds are drawn).
    """

    batch: int
    n_batches: int
    loss: float
    balanced_accuracy: float
    stage: str = "train"


TrainingProgressCallback = Callable[[TrainingProgress], None]


def training_classes(
    totals: NDArray[np.int64], wanted: Sequence[int], scans: Sequence[str]
) -> list[int]:
    """The label values a run trains on, sorted: ``wanted``, or every one with points.

    Args:
        totals: points per label value over the training scans (index = value, 0..8).
        wanted: the configuration's classes (empty: every class present).
        scans: the training scans' names (for messages).

    Raises:
        TrainingDataError: a wanted class has no point, or fewer than two classes.
    """
    present = [v for v in range(1, N_CLASSES + 1) if totals[v] > 0]
    classes = list(wanted) or present
    missing = [v for v in classes if totals[v] == 0]
    if missing:
        listed = ", ".join(f"{v} ({class_by_value(v).name})" for v in missing)
        raise TrainingDataError(
            f"class(es) {listed} have no labelled point in the training scans {list(scans)}: "
            "remove them from [training] classes or add scans"
        )
    if len(classes) < 2:
        raise TrainingDataError(
            f"training needs at least 2 labelled classes, found {classes or 'none'} in "
            f"{list(scans)}"
        )
    return sorted(classes)


def balanced_accuracy(confusion: NDArray[np.int64]) -> float:
    """Mean recall over the rows (true classes) that have samples; NaN when none has."""
    totals = confusion.sum(axis=1)
    seen = totals > 0
    if not seen.any():
        return math.nan
    return float(np.mean(np.diag(confusion)[seen] / totals[seen]))


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """``torch.save(state)`` to ``path`` through a temporary sibling renamed into place."""
    torch: Any = require("torch", "torch")
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.partial")
    try:
        torch.save(state, temp)
        temp.replace(path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def load_checkpoint(path: Path, *, version: int) -> dict[str, Any]:
    """The state :func:`save_checkpoint` wrote (tensors on the CPU, no arbitrary pickle).

    Raises:
        CheckpointError: not a checkpoint, or one of another ``version``.
    """
    torch: Any = require("torch", "torch")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds on a file that is not its own
        raise CheckpointError(f"{path}: not a training checkpoint: {exc}") from exc
    if not isinstance(state, dict) or state.get("format") != version:
        raise CheckpointError(f"{path}: expected checkpoint format {version}")
    return state
