"""Cube maps and the image baseline: rendering speed and memory, inference, accuracy.

Run: ``.venv/bin/python benchmarks/bench_cubemap.py [--points 200000] [--size 512]``

Options of the accuracy section: ``--preset small|paper`` (the image baseline's preset,
default ``small``), ``--face-size N`` (classification face edge, overriding the preset's),
``--variants boosted,unet`` (which variants to train, default both), ``--epochs N`` (U-Net
epochs, overriding the preset's), ``--no-covariance`` (skip the covariance comparison),
``--json PATH`` (also write the report there). The U-Net's mean training loss of each
epoch (its ``loss_history_``) goes into the report; training stages are printed as they go.

1. Rendering points/s and peak traced memory of ``viz.cubemap.render_cubemap`` (numba
   z-buffer) against a straightforward numpy implementation (vectorised projection, a
   lexsort per chunk, merged into the faces), same points, same run; both from points
   already in memory, so file parsing is not timed.
2. Per-face inference time of both variants, end-to-end points/s of ``predict_image_scan``.
3. Accuracy on simulated scans: train on the three stations of ``street`` seed 1, test on
   the three stations of ``street`` seed 2 (another layout), both variants, and the
   covariance baseline on the same split: mIoU, OA, per-class IoU, train and predict
   wall / CPU seconds.
Wall and CPU seconds are printed side by side (the machine may be shared).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from semantic3d.core import PointCloud


def numpy_render(
    chunks: list[PointCloud], station: tuple[float, float, float], size: int
) -> np.ndarray:
    """Index faces the numpy way: project, lexsort (pixel, range), merge per chunk."""
    from semantic3d.viz.cubemap import face_bases

    bases = face_bases()
    depth = np.full(6 * size * size, np.inf, np.float32)
    index = np.full(6 * size * size, -1, np.int64)
    begin = 0
    for chunk in chunks:
        d = chunk.xyz - np.asarray(station)
        magnitude = np.abs(d)
        axis = np.argmax(magnitude, axis=1)
        negative = d[np.arange(len(d)), axis] < 0
        face = np.array([0, 2, 1, 3, 4, 5])[axis * 2 + negative]
        forward = np.einsum("ij,ij->i", d, bases[face, 0])
        u = np.einsum("ij,ij->i", d, bases[face, 1]) / forward
        v = np.einsum("ij,ij->i", d, bases[face, 2]) / forward
        col = np.clip(np.floor((u + 1) * 0.5 * size), 0, size - 1).astype(np.int64)
        row = np.clip(np.floor((1 - v) * 0.5 * size), 0, size - 1).astype(np.int64)
        flat = (face * size + row) * size + col
        rng = np.sqrt((d * d).sum(axis=1)).astype(np.float32)
        positions = np.arange(begin, begin + len(d))
        order = np.lexsort((positions, rng, flat))
        first = np.ones(order.size, bool)
        first[1:] = flat[order][1:] != flat[order][:-1]
        pick = order[first]
        closer = rng[pick] < depth[flat[pick]]
        depth[flat[pick][closer]] = rng[pick][closer]
        index[flat[pick][closer]] = positions[pick][closer]
        begin += len(d)
    return index.reshape(6, size, size)


def timed(run: Callable[[], Any]) -> tuple[Any, float, float, float]:
    """Result, wall s, CPU s, peak traced MB."""
    tracemalloc.start()
    wall, cpu = time.perf_counter(), time.process_time()
    result = run()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return result, wall, cpu, peak


def miou(truth: np.ndarray, predicted: np.ndarray) -> tuple[float, float, dict[str, float]]:
    """Mean IoU, overall accuracy and IoU per class name over labelled points (the
    benchmark's convention: absent classes NaN, left out of the mean)."""
    from semantic3d.core.classes import CLASSES
    from semantic3d.metrics.confusion import ConfusionMatrix

    matrix = ConfusionMatrix()
    matrix.update(truth, predicted)
    scores = matrix.compute_scores()
    per_class = {c.name: float(v) for c, v in zip(CLASSES, scores.iou, strict=True)}
    return float(scores.mean_iou), float(scores.overall_accuracy), per_class


def value_counts(labels: np.ndarray) -> dict[int, int]:
    """Points per label value."""
    values, counts = np.unique(labels, return_counts=True)
    return {int(v): int(c) for v, c in zip(values, counts, strict=True)}


class TrainingLog:
    """A training ``progress`` callback: prints each stage as it goes."""

    def __init__(self) -> None:
        self.started = time.perf_counter()

    def __call__(self, stage: str, done: int, total: int) -> None:
        print(f"  {stage} {done}/{total} ({time.perf_counter() - self.started:.0f} s)", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=200_000, help="points per station")
    parser.add_argument("--size", type=int, default=512, help="face edge of the render timing")
    parser.add_argument("--preset", default="small", choices=("small", "paper"))
    parser.add_argument("--face-size", type=int, help="classification face edge (preset's)")
    parser.add_argument("--variants", default="boosted,unet", help="comma-separated: boosted, unet")
    parser.add_argument("--epochs", type=int, help="U-Net epochs (default: the preset's)")
    parser.add_argument("--no-accuracy", action="store_true")
    parser.add_argument("--no-covariance", action="store_true")
    parser.add_argument("--json", type=Path, help="also write the report to this file")
    args = parser.parse_args()

    from semantic3d.baselines.common.scans import LabelledScan
    from semantic3d.baselines.image.config import ImageConfig, preset_config
    from semantic3d.baselines.image.model import ImageVariant
    from semantic3d.baselines.image.predict import predict_image_scan
    from semantic3d.baselines.image.training import train_image_model
    from semantic3d.datasets.simulator import simulate
    from semantic3d.io.formats import iter_points
    from semantic3d.io.labels import read_labels
    from semantic3d.viz.cubemap import render_cubemap

    variants = [ImageVariant(v.strip()) for v in args.variants.split(",") if v.strip()]
    report: dict[str, Any] = {"points_per_scan": args.points, "face_size": args.size}
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        runs = {
            seed: simulate(
                "street", out=folder / f"s{seed}", n_points=args.points, seed=seed, stations=3
            )
            for seed in (1, 2)
        }
        scan = runs[1].scans[0]
        station = scan.station.position
        chunks = list(iter_points(scan.points_path, chunk_size=1 << 18))
        n = sum(c.n_points for c in chunks)
        render_cubemap(chunks[:1], station=station, size=8)  # compile outside the timing
        for name, run in (
            ("numba r=0", lambda: render_cubemap(chunks, station=station, size=args.size)),
            (
                "numba r=1",
                lambda: render_cubemap(chunks, station=station, size=args.size, splat_radius_px=1),
            ),
            ("numpy r=0", lambda: numpy_render(chunks, station, args.size)),
        ):
            result, wall, cpu, peak = timed(run)
            report[f"render {name}"] = {
                "points_per_s": n / wall,
                "wall_s": wall,
                "cpu_s": cpu,
                "peak_traced_mb": peak,
            }
            print(
                f"render {name}: {n / wall:,.0f} points/s (wall {wall:.2f} s, cpu {cpu:.2f} s), peak {peak:.0f} MB"
            )
        same = np.array_equal(
            render_cubemap(chunks, station=station, size=args.size).point_index,
            numpy_render(chunks, station, args.size),
        )
        report["numpy_equals_numba"] = bool(same)
        print("numpy index faces equal numba's:", same)
        if args.no_accuracy:
            finish(report, args.json)
            return

        def labelled(result: Any) -> list[LabelledScan]:
            return [
                LabelledScan(s.points_path.stem, s.points_path, s.labels_path) for s in result.scans
            ]

        train, test = labelled(runs[1]), labelled(runs[2])
        config: ImageConfig = preset_config(args.preset)
        if args.face_size is not None:
            config = dataclasses.replace(
                config, faces=dataclasses.replace(config.faces, size=args.face_size)
            )
        if args.epochs is not None:
            config = dataclasses.replace(
                config, unet=dataclasses.replace(config.unet, epochs=args.epochs)
            )
        report["image_config"] = {
            "preset": config.preset,
            "face_size": config.faces.size,
            "unet_epochs": config.unet.epochs,
        }
        for variant in variants:
            log = TrainingLog()
            model, wall, cpu, _ = timed(
                lambda v=variant, g=log: train_image_model(
                    train, config=config, variant=v, progress=g
                )
            )
            print(f"  trained in {wall:.0f} s (cpu {cpu:.0f} s)", flush=True)
            truths, preds = [], []
            pred_wall = pred_cpu = 0.0
            n_points = 0
            for scan_ in test:
                out = folder / f"pred_{variant}" / f"{scan_.name}.labels"
                result, w, c, _ = timed(
                    lambda s=scan_, o=out, m=model: predict_image_scan(m, s.points_path, out_path=o)
                )
                pred_wall, pred_cpu = pred_wall + w, pred_cpu + c
                n_points += result.run.n_points
                truths.append(read_labels(scan_.labels_path))
                preds.append(read_labels(out))
            cubemap = render_cubemap(
                iter_points(test[0].points_path),
                station=model.training_stations[0],
                size=config.faces.size,
            )
            from semantic3d.baselines.image.faces import cube_faces

            face = cube_faces(cubemap)[0]
            _, face_wall, face_cpu, _ = timed(lambda m=model, f=face: m.segmenter.segment(f))
            truth, predicted = np.concatenate(truths), np.concatenate(preds)
            m, oa, per_class = miou(truth, predicted)
            report[f"image {variant}"] = {
                "train_wall_s": wall,
                "train_cpu_s": cpu,
                "per_face_wall_s": face_wall,
                "per_face_cpu_s": face_cpu,
                "end_to_end_points_per_s": n_points / pred_wall,
                "predict_wall_s": pred_wall,
                "predict_cpu_s": pred_cpu,
                "mean_iou": m,
                "overall_accuracy": oa,
                "iou_per_class": per_class,
                "points_per_predicted_value": value_counts(predicted),
                "points_per_true_value": value_counts(truth),
            }
            losses = getattr(model.segmenter, "loss_history_", None)
            if losses:  # the U-Net's mean training loss per epoch
                report[f"image {variant}"]["epoch_losses"] = losses
            print(
                f"image {variant}: mIoU {m:.3f} OA {oa:.3f}; train {wall:.0f} s (cpu {cpu:.0f}); "
                f"face {face_wall:.2f} s (cpu {face_cpu:.2f}); end to end {n_points / pred_wall:,.0f} points/s; "
                f"predict {pred_wall:.0f} s (cpu {pred_cpu:.0f})",
                flush=True,
            )
        if args.no_covariance:
            finish(report, args.json)
            return
        try:
            from semantic3d.baselines.covariance.config import (
                CovarianceConfig,
                ForestConfig,
                PredictionConfig,
                SamplingConfig,
            )
            from semantic3d.baselines.covariance.predict import predict_scan as predict_covariance
            from semantic3d.baselines.covariance.training import train_covariance_model
            from semantic3d.features import FeatureConfig

            cov_config = CovarianceConfig(
                features=FeatureConfig(base_voxel_size_m=0.1, n_levels=6, k_neighbours=10),
                forest=ForestConfig(n_estimators=30, max_depth=15),
                sampling=SamplingConfig(points_per_class=2000, seed=0),
                prediction=PredictionConfig(tile_size_m=12.8),
            )
            model, wall, cpu, _ = timed(lambda: train_covariance_model(train, config=cov_config))
            truths, preds = [], []
            for scan_ in test:
                out = folder / "pred_cov" / f"{scan_.name}.labels"
                predict_covariance(model, scan_.points_path, out_path=out)
                truths.append(read_labels(scan_.labels_path))
                preds.append(read_labels(out))
            m, oa, per_class = miou(np.concatenate(truths), np.concatenate(preds))
            report["covariance"] = {
                "mean_iou": m,
                "overall_accuracy": oa,
                "iou_per_class": per_class,
                "train_wall_s": wall,
            }
            print(f"covariance: mIoU {m:.3f} OA {oa:.3f}")
        except Exception as exc:  # the comparison is optional: report why it is missing
            report["covariance"] = f"not run: {exc}"
            print("covariance not run:", exc)
    finish(report, args.json)


def finish(report: dict[str, Any], path: Path | None) -> None:
    """Print the report as JSON, and write it to ``path`` when given."""
    text = json.dumps(report, indent=2)
    print(text)
    if path is not None:
        path.write_text(text + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
