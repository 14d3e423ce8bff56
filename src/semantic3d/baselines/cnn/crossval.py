"""Cross-validation of the CNN baseline with folds grouped by scan.

Scan ``i`` of the sorted list goes to fold ``i mod n_folds``: each fold's scans are held
out, a model is trained on the others and labels the held-out scans through the same
tiled prediction as ``predict``. Scores (:mod:`semantic3d.metrics`) are pooled over the
folds' confusion matrices. ``points_per_scan`` labels a random sample of each held-out
scan instead of every point (a CPU labels a few hundred points a second).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.training import Progress, train_cnn_model
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.metrics import ConfusionMatrix
from semantic3d.metrics.scores import Scores

__all__ = [
    "CrossValidationResult",
    "FoldResult",
    "cross_validate",
    "evaluation_sample",
    "scan_folds",
]


@dataclass(frozen=True, slots=True)
class FoldResult:
    """One fold: what it trained on, what it labelled, how well.

    Attributes:
        train_scans: names of its training scans.
        test_scans: names of its held-out scans.
        confusion: its ``(8, 8)`` confusion matrix (rows truth, columns prediction).
        n_points: held-out points labelled.
        training_time_s: wall time of its training.
        prediction_time_s: wall time of labelling its held-out points.
    """

    train_scans: tuple[str, ...]
    test_scans: tuple[str, ...]
    confusion: NDArray[np.int64]
    n_points: int
    training_time_s: float
    prediction_time_s: float

    @property
    def scores(self) -> Scores:
        """Scores of this fold."""
        from semantic3d.metrics.scores import compute_scores

        return compute_scores(self.confusion)


@dataclass(frozen=True, slots=True)
class CrossValidationResult:
    """Every fold, and the scores of their pooled confusion matrix."""

    folds: tuple[FoldResult, ...]

    @property
    def scores(self) -> Scores:
        """Scores of the summed confusion matrices."""
        from semantic3d.metrics.scores import compute_scores

        return compute_scores(sum(fold.confusion for fold in self.folds))


def scan_folds(names: Sequence[str], n_folds: int) -> list[tuple[str, ...]]:
    """The held-out scans of each fold: sorted scan ``i`` in fold ``i mod n_folds``.

    >>> scan_folds(["c", "a", "b"], 2)
    [('a', 'c'), ('b',)]
    """
    if n_folds < 2 or n_folds > len(names):
        raise TrainingDataError(
            f"cross-validation grouped by scan: expected 2..{len(names)} folds for "
            f"{len(names)} scans, found {n_folds}"
        )
    ordered = sorted(names)
    return [tuple(ordered[i::n_folds]) for i in range(n_folds)]


def evaluation_sample(
    n_points: int, points_per_scan: int | None, *, seed: int, fold: int, scan: int
) -> NDArray[np.int64] | None:
    """The sorted indices of the held-out points a fold labels (None: every point).

    Drawn from ``(seed, fold, scan)``, so another method can be scored on the same points.
    """
    if points_per_scan is None or points_per_scan >= n_points:
        return None
    rng = np.random.default_rng((seed, fold, scan))
    return np.sort(rng.choice(n_points, points_per_scan, replace=False))


def cross_validate(
    scans: Sequence[LabelledScan],
    *,
    config: CnnConfig,
    n_folds: int,
    points_per_scan: int | None = None,
    device: str = "cpu",
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    on_fold: Callable[[int, FoldResult], None] | None = None,
) -> CrossValidationResult:
    """Train and evaluate one model per fold (see the module docs).

    Args:
        scans: labelled scans (at least ``n_folds``).
        config: the configuration of every fold's training.
        n_folds: folds; scans are assigned round-robin in name order.
        points_per_scan: label this many randomly drawn points per held-out scan (seeded
            by ``training.seed``); None labels every point.
        device: ``cpu`` or ``cuda``.
        workdir: scratch folder.
        progress: training progress of the current fold.
        on_fold: called as each fold finishes.
    """
    from semantic3d.io.formats import iter_points

    by_name = {scan.name: scan for scan in scans}
    folds: list[FoldResult] = []
    for number, held_out in enumerate(scan_folds(list(by_name), n_folds)):
        train = [by_name[n] for n in sorted(by_name) if n not in held_out]
        model = train_cnn_model(
            train, config=config, device=device, workdir=workdir, progress=progress
        )
        model.to(device)
        matrix = ConfusionMatrix()
        started = time.perf_counter()
        n_points = 0
        for position, name in enumerate(held_out):
            scan = by_name[name]
            truth = np.concatenate(list(scan.iter_labels()))
            select = evaluation_sample(
                truth.size, points_per_scan, seed=config.training.seed, fold=number, scan=position
            )
            with tempfile.TemporaryDirectory(prefix="s3d-cnn-cv-", dir=workdir) as scratch:
                chunks = iter_points(scan.points_path, chunk_size=config.prediction.chunk_size)
                for block in model.iter_labelled_blocks(
                    chunks, workdir=Path(scratch), select=select
                ):
                    matrix.update(truth[block.point_indices], block.labels)
                    n_points += block.point_indices.size
        fold = FoldResult(
            train_scans=tuple(s.name for s in train),
            test_scans=held_out,
            confusion=matrix.compute(),
            n_points=n_points,
            training_time_s=model.training_time_s,
            prediction_time_s=time.perf_counter() - started,
        )
        folds.append(fold)
        if on_fold is not None:
            on_fold(number, fold)
    return CrossValidationResult(tuple(folds))
