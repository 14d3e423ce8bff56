"""``semantic3d demo``: the main job on embedded defaults, end to end.

1. the real samples in ``../shared/data`` (when present): summarised and converted to the
   binary cache, LAS and PLY;
2. a simulated terrestrial scan of a default scene, two stations;
3. the covariance baseline trained on one station and run on the other;
4. the prediction evaluated with the benchmark's protocol, reports written;
5. optionally, the benchmark server started with the result on its leaderboard.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import guarded, progress_bar, threads_option

if TYPE_CHECKING:
    from semantic3d.evaluation.result import EvaluationResult, MethodInfo

DEFAULT_DATA = Path("..") / "shared" / "data"


def demo(
    out: Path = typer.Option(
        Path("demo-output"), help="Folder for everything the demo writes (rewritten on each run)."
    ),
    data: Path = typer.Option(
        DEFAULT_DATA, help="Real labelled samples (NAME.txt + NAME.labels); skipped when absent."
    ),
    scene: str = typer.Option("square", help="Simulated scene: village, street, square, railway."),
    points: int = typer.Option(400_000, min=1, help="Points per simulated station."),
    seed: int = typer.Option(0, help="Seed of the simulation and the baseline."),
    serve: bool = typer.Option(
        False, "--serve/--no-serve", help="Start the benchmark server at the end."
    ),
    port: int = typer.Option(8000, help="Port of the benchmark server."),
    threads: int | None = threads_option(),
) -> None:
    """Run the main job end to end on embedded defaults."""
    started = time.perf_counter()
    with guarded():
        if serve:  # a busy port is said now, not after the demo's minutes of work
            from semantic3d.server.serving import check_port_free

            check_port_free("127.0.0.1", port)
        out.mkdir(parents=True, exist_ok=True)
        if data.is_dir() and any(data.glob("*/*.txt")):
            _real_samples(data, out / "samples")
        else:
            ui.console.print(f"[dim]no real samples in {data}: skipping step 1[/]")
        simulated = _simulate(out / "simulated", scene=scene, points=points, seed=seed)
        result = _baseline_and_evaluate(simulated, out, seed=seed)
        ui.console.print(
            f"\n[bold green]demo finished[/] in {time.perf_counter() - started:.0f} s: "
            f"mIoU {result.scores.mean_iou:.3f}, OA {result.scores.overall_accuracy:.3f}; "
            f"report in {out / 'report.html'}"
        )
    if serve:
        from semantic3d.cli.server import serve_demo

        serve_demo(
            out,
            result=result,
            ground_truth=out / "challenge",
            predictions=out / "submission",
            port=port,
        )


def _real_samples(data: Path, out: Path) -> None:
    from rich.table import Table

    from semantic3d.io.conversion import build_cache
    from semantic3d.io.formats import iter_points, summarize_points, write_points

    ui.console.rule("1. real labelled samples")
    out.mkdir(parents=True, exist_ok=True)
    table = Table("sample", "points", "classes present", "written")
    for points_path in sorted(data.glob("*/*.txt")):
        summary = summarize_points(points_path)
        cache = out / f"{points_path.stem}.cache"
        build_cache(points_path, cache, labels_path=points_path.with_suffix(".labels"))
        for suffix in (".las", ".ply"):
            write_points(out / f"{points_path.stem}{suffix}", iter_points(cache))
        present = (
            ""
            if summary.label_counts is None
            else " ".join(str(v) for v in range(1, 9) if summary.label_counts[v])
        )
        table.add_row(points_path.stem, f"{summary.n_points:,}", present, ".cache .las .ply")
    ui.console.print(table)


def _simulate(out: Path, *, scene: str, points: int, seed: int) -> list[tuple[Path, Path]]:
    from rich.table import Table

    from semantic3d.core.classes import CLASSES
    from semantic3d.datasets.simulator import simulate

    ui.console.rule(f"2. simulated terrestrial scans ({scene}, 2 stations)")
    if out.exists():
        shutil.rmtree(out)
    with progress_bar() as bar:
        task = bar.add_task("simulating", total=None)
        result = simulate(
            scene,
            out=out,
            n_points=points,
            stations=2,
            seed=seed,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )
    table = Table("class", *[scan.points_path.name for scan in result.scans])
    for cls in CLASSES:
        table.add_row(cls.name, *[f"{scan.class_counts[cls.value]:,}" for scan in result.scans])
    table.add_row("[bold]all points", *[f"[bold]{scan.n_points:,}" for scan in result.scans])
    ui.console.print(table)
    return [(scan.points_path, scan.labels_path) for scan in result.scans]


def _baseline_and_evaluate(
    scans: list[tuple[Path, Path]], out: Path, *, seed: int
) -> EvaluationResult:
    import numpy as np
    from rich.table import Table

    from semantic3d.core.classes import CLASSES
    from semantic3d.evaluation.challenge import custom_challenge
    from semantic3d.evaluation.evaluate import evaluate_submission
    from semantic3d.evaluation.report import write_html, write_json, write_markdown

    (train_points, train_labels), (test_points, test_labels) = scans[0], scans[1]
    ui.console.rule("3. covariance baseline")
    baseline = out / "baseline"
    baseline.mkdir(parents=True, exist_ok=True)
    method, predicted = _run_baseline(train_points, train_labels, test_points, baseline, seed=seed)
    ui.console.rule("4. evaluation")
    ground_truth = out / "challenge"
    ground_truth.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(test_labels, ground_truth / test_labels.name)
    # A submission holds only .labels files named as the ground truth's.
    predictions = out / "submission"
    shutil.rmtree(predictions, ignore_errors=True)
    predictions.mkdir()
    shutil.copyfile(predicted, predictions / test_labels.name)
    challenge = custom_challenge(ground_truth, name="demo")
    result = evaluate_submission(predictions, challenge=challenge, method=method)
    write_json(out / "result.json", result)
    write_markdown(out / "report.md", result)
    write_html(out / "report.html", result)
    table = Table("class", "IoU")
    for cls, iou in zip(CLASSES, result.scores.iou, strict=True):
        table.add_row(cls.name, "absent" if np.isnan(iou) else f"{iou:.3f}")
    ui.console.print(table)
    return result


def _run_baseline(
    train_points: Path, train_labels: Path, test_points: Path, out: Path, *, seed: int
) -> tuple[MethodInfo, Path]:
    from semantic3d.baselines.covariance.config import CovarianceConfig, SamplingConfig
    from semantic3d.baselines.covariance.persistence import save_model
    from semantic3d.baselines.covariance.predict import predict_scan
    from semantic3d.baselines.covariance.training import LabelledScan, train_covariance_model
    from semantic3d.evaluation.result import MethodInfo

    config = CovarianceConfig(sampling=SamplingConfig(seed=seed))
    scans = [LabelledScan(train_points.stem, train_points, train_labels)]
    with progress_bar() as bar:
        task = bar.add_task("training (features + forest)", total=None)
        model = train_covariance_model(
            scans,
            config=config,
            progress=lambda stage, done, total: bar.update(
                task, description=f"training: {stage}", completed=done, total=total
            ),
        )
        save_model(model, out / "covariance.model")
        task = bar.add_task(f"predicting {test_points.name}", total=None)
        run = predict_scan(
            model,
            test_points,
            out_path=out / f"{test_points.stem}.labels",
            progress=lambda done, total: bar.update(task, completed=done, total=total),
            overwrite=True,  # the demo's own folder, rewritten on every run
        )
    ui.console.print(
        f"trained on {model.training_scans[0]} in {model.training_time_s:.1f} s; "
        f"labelled {run.n_points:,} points in {run.runtime_s:.1f} s "
        f"({run.points_per_second / 1e3:.0f} k points/s)"
    )
    method = MethodInfo(
        name="covariance baseline (TMLC-MS)",
        runtime_s=run.runtime_s,
        hardware=run.hardware.describe(),
        description="Multi-scale covariance features on a voxel pyramid and a random forest "
        "(Hackel, Wegner & Schindler 2016), trained on one simulated station.",
    )
    return method, Path(run.labels_path)


def register(app: typer.Typer) -> None:
    """Add ``demo`` to ``app``."""
    app.command("demo")(demo)
