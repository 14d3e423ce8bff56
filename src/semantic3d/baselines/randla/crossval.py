"""Cross-validation of the RandLA-Net baseline with folds grouped by scan.

Each fold's scans are held out (:func:`~semantic3d.baselines.common.crossval.scan_folds`:
sorted scan ``i`` in fold ``i mod n_folds``, or folds given), a model is trained on the
others and labels every point of the held-out scans through the same tiled prediction as
``predict``. Scores are pooled over the folds' confusion matrices.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from semantic3d.baselines.common.crossval import CrossValidationResult, FoldResult, scan_folds
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.baselines.common.training import TrainingProgressCallback
from semantic3d.baselines.randla.config import RandlaConfig
from semantic3d.baselines.randla.training import train_randla_model
from semantic3d.metrics import ConfusionMatrix

__all__ = ["cross_validate"]


def cross_validate(
    scans: Sequence[LabelledScan],
    *,
    config: RandlaConfig,
    n_folds: int = 5,
    folds: Sequence[Sequence[str]] | None = None,
    device: str = "cpu",
    workdir: str | Path | None = None,
    progress: TrainingProgressCallback | None = None,
    on_fold: Callable[[int, FoldResult], None] | None = None,
) -> CrossValidationResult:
    """Train and evaluate one model per fold (see the module docs).

    Args:
        scans: labelled scans (at least ``n_folds``).
        config: the configuration of every fold's training.
        n_folds: folds when ``folds`` is None; scans are assigned round-robin in name order.
        folds: the held-out scan names of each fold (every scan in exactly one).
        device: ``cpu`` or ``cuda``.
        workdir: scratch folder.
        progress: training progress of the current fold.
        on_fold: called as each fold finishes.

    Raises:
        TrainingDataError: a bad fold count, or folds that do not partition the scans.
    """
    from semantic3d.io.formats import iter_points

    by_name = {scan.name: scan for scan in scans}
    if folds is None:
        held_out_sets = scan_folds(list(by_name), n_folds)
    else:
        held_out_sets = [tuple(fold) for fold in folds]
        named = sorted(name for fold in held_out_sets for name in fold)
        if named != sorted(by_name):
            raise TrainingDataError(
                f"folds: expected every scan of {sorted(by_name)} in exactly one fold, "
                f"found {named}"
            )
    results: list[FoldResult] = []
    for number, held_out in enumerate(held_out_sets):
        train = [by_name[n] for n in sorted(by_name) if n not in held_out]
        model = train_randla_model(
            train, config=config, device=device, workdir=workdir, progress=progress
        )
        model.to(device)
        matrix = ConfusionMatrix()
        started = time.perf_counter()
        n_points = 0
        for name in held_out:
            scan = by_name[name]
            truth = np.concatenate(list(scan.iter_labels()))
            with tempfile.TemporaryDirectory(prefix="s3d-randla-cv-", dir=workdir) as scratch:
                chunks = iter_points(scan.points_path, chunk_size=config.prediction.chunk_size)
                for block in model.iter_labelled_blocks(chunks, workdir=Path(scratch)):
                    matrix.update(truth[block.point_indices], block.labels)
                    n_points += block.point_indices.size
        fold = FoldResult(
            train_scans=tuple(s.name for s in train),
            test_scans=tuple(held_out),
            confusion=matrix.compute(),
            n_points=n_points,
            training_time_s=model.training_time_s,
            prediction_time_s=time.perf_counter() - started,
        )
        results.append(fold)
        if on_fold is not None:
            on_fold(number, fold)
    return CrossValidationResult(tuple(results))
