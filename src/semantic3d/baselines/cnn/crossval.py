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
from pathlib import Path

import numpy as np

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.training import Progress, train_cnn_model
from semantic3d.baselines.common.crossval import (
    CrossValidationResult,
    FoldResult,
    evaluation_sample,
    scan_folds,
)
from semantic3d.baselines.common.scans import LabelledScan
from semantic3d.metrics import ConfusionMatrix

__all__ = [
    "CrossValidationResult",
    "FoldResult",
    "cross_validate",
    "evaluation_sample",
    "scan_folds",
]


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
