"""Shortened cross-validation of the CNN baseline on CMU Oakland, beside the covariance baseline.

The 10 Oakland scans (Munoz et al., CVPR 2009) are split into folds grouped by scan
(sorted scan ``i`` in fold ``i mod n``, :func:`semantic3d.baselines.cnn.scan_folds`). For
each fold, DeepNet (the paper's network and cubes) is trained on the other scans for
``--batches`` class-balanced batches of 100 -- a *shortened* schedule, the paper's is
74,700 -- and labels ``--points-per-scan`` randomly drawn points of each held-out scan.
The covariance baseline (default configuration) is trained on the same scans and scored
on the same drawn points, and on every point. Writes ``benchmarks/out/cv_cnn_oakland.json``.

Usage: ``python benchmarks/cv_cnn_oakland.py --folds 2 --batches 150 --points-per-scan 1000``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.crossval import cross_validate, evaluation_sample, scan_folds
from semantic3d.baselines.common.scans import find_labelled_scans
from semantic3d.metrics import ConfusionMatrix
from semantic3d.metrics.scores import compute_scores

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"


def covariance_on_folds(
    scans: list[Any], folds: list[tuple[str, ...]], *, points_per_scan: int, seed: int
) -> dict[str, Any]:
    """Train the covariance baseline per fold; score it on the CNN's points and on all."""
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.predict import predict_scan
    from semantic3d.baselines.covariance.training import build_training_set, fit_model
    from semantic3d.io.labels import read_labels

    config = CovarianceConfig()
    by_name = {s.name: s for s in scans}
    sampled, everything = ConfusionMatrix(), ConfusionMatrix()
    started = time.perf_counter()
    for number, held_out in enumerate(folds):
        train = [by_name[n] for n in sorted(by_name) if n not in held_out]
        model = fit_model(build_training_set(train, config=config), config=config)
        for position, name in enumerate(held_out):
            scan = by_name[name]
            with tempfile.TemporaryDirectory() as scratch:
                run = predict_scan(model, scan.points_path, out_path=Path(scratch) / "p.labels")
                predicted = read_labels(run.labels_path)
            truth = np.concatenate(list(scan.iter_labels()))
            everything.update(truth, predicted)
            select = evaluation_sample(
                truth.size, points_per_scan, seed=seed, fold=number, scan=position
            )
            chosen = np.arange(truth.size) if select is None else select
            sampled.update(truth[chosen], predicted[chosen])
    return {
        "sampled": _scores(sampled.compute()),
        "all_points": _scores(everything.compute()),
        "seconds": time.perf_counter() - started,
    }


def _scores(matrix: Any) -> dict[str, Any]:
    scores = compute_scores(matrix)
    return {
        "mean_iou": float(scores.mean_iou),
        "overall_accuracy": float(scores.overall_accuracy),
        "iou": [None if np.isnan(v) else round(float(v), 4) for v in scores.iou],
        "n_points": int(scores.n_points),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "oakland")
    parser.add_argument("--folds", type=int, default=2)
    parser.add_argument("--batches", type=int, default=150)
    parser.add_argument("--points-per-scan", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"{args.data}: the Oakland samples are not here")
    scans = list(find_labelled_scans(args.data))
    folds = scan_folds([s.name for s in scans], args.folds)
    base = CnnConfig()
    config = dataclasses.replace(
        base,
        training=dataclasses.replace(
            base.training, n_batches=args.batches, seed=args.seed, checkpoint_every=0
        ),
    )
    print(f"folds: {folds}", flush=True)
    last = [0.0]

    def progress(state: Any) -> None:
        now = time.perf_counter()
        if state.stage == "train" and (now - last[0] > 60 or state.batch == state.n_batches):
            last[0] = now
            print(
                f"  batch {state.batch}/{state.n_batches} loss {state.loss:.3f} "
                f"balanced accuracy {state.balanced_accuracy:.3f}",
                flush=True,
            )

    cpu, wall = time.process_time(), time.perf_counter()
    result = cross_validate(
        scans,
        config=config,
        n_folds=args.folds,
        points_per_scan=args.points_per_scan,
        progress=progress,
        on_fold=lambda n, f: print(
            f"fold {n}: mIoU {f.scores.mean_iou:.3f} OA {f.scores.overall_accuracy:.3f} "
            f"train {f.training_time_s:.0f} s, label {f.n_points} points in "
            f"{f.prediction_time_s:.0f} s",
            flush=True,
        ),
    )
    cnn = {
        **_scores(sum(f.confusion for f in result.folds)),
        "wall_s": time.perf_counter() - wall,
        "cpu_s": time.process_time() - cpu,
        "training_s": [f.training_time_s for f in result.folds],
        "prediction_s": [f.prediction_time_s for f in result.folds],
    }
    print(f"cnn (shortened, {args.batches} batches): {cnn}", flush=True)
    covariance = covariance_on_folds(
        scans, folds, points_per_scan=args.points_per_scan, seed=args.seed
    )
    print(f"covariance: {covariance}", flush=True)
    OUT.mkdir(exist_ok=True)
    document = {
        "folds": folds,
        "batches": args.batches,
        "points_per_scan": args.points_per_scan,
        "cnn": cnn,
        "covariance": covariance,
    }
    (OUT / "cv_cnn_oakland.json").write_text(json.dumps(document, indent=2) + "\n")


if __name__ == "__main__":
    main()
