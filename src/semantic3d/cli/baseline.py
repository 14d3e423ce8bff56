"""``semantic3d baseline covariance train | predict | cv``: the 3D covariance baseline.

Thin shells over :mod:`semantic3d.baselines.covariance`: parse arguments, call the library
with a progress bar, print a summary. scikit-learn is imported when a command runs.
"""

from __future__ import annotations

import dataclasses
import json
import math
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.baseline_common import (
    OVERWRITE_HELP,
    SCANS_HELP,
    ChallengeChoice,
    challenge_option,
    data_option,
    out_option,
    print_runs,
    scan_argument,
    scan_names,
    scans_and_target,
    scans_progress,
)
from semantic3d.cli.cluster import open_cluster, scheduler_option, workers_option
from semantic3d.cli.console import (
    MARKUP_MODE,
    escape,
    guarded,
    plural,
    progress_bar,
    refuse_existing,
    threads_option,
)

if TYPE_CHECKING:
    from semantic3d.baselines.common.prediction import Predictor
    from semantic3d.baselines.common.submission import ScanToLabel
    from semantic3d.baselines.covariance.config import CovarianceConfig

baseline_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="Baselines: train, predict and cross-validate.",
    no_args_is_help=True,
)
covariance_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="3D covariance baseline (Hackel et al. 2016): multi-scale features + random forest.",
    no_args_is_help=True,
)
baseline_app.add_typer(covariance_app, name="covariance")

_CONFIG_HELP = (
    "TOML configuration with the sections features, forest, sampling, prediction, grid_search."
)


def _config(path: Path | None, seed: int | None) -> CovarianceConfig:
    from semantic3d.baselines.covariance.config import CovarianceConfig, load_config

    config = load_config(path) if path is not None else CovarianceConfig()
    if seed is not None:
        config = dataclasses.replace(
            config, sampling=dataclasses.replace(config.sampling, seed=seed)
        )
    return config


@covariance_app.command()
def train(
    data: Path = typer.Option(..., "--data", help="Folder of NAME.txt + NAME.labels scans."),
    out: Path = typer.Option(..., "--out", help="Model file to write."),
    scans: list[str] = typer.Option([], "--scans", help=SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    seed: int | None = typer.Option(
        None, "--seed", help="Override the seed of the sampling section."
    ),
    grid_search: bool = typer.Option(
        False,
        "--grid-search",
        help="Choose the forest by the [grid_search] grid, cross-validated with folds grouped "
        "by scan, then fit it (as [grid_search] select_forest = true); the chosen parameters "
        "are recorded in the model file.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    workdir: Path | None = typer.Option(
        None, "--workdir", help="Scratch folder for tiles (with --scheduler: one the workers see)."
    ),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    threads: int | None = threads_option(),
) -> None:
    """Train on labelled scans (class-balanced sample) and save the model.

    With --scheduler or --workers the scans are read and the training points described on
    the Dask cluster, tile by tile; the forest is fitted here. The model is the same.
    """
    with guarded():
        refuse_existing([out], overwrite=overwrite)
        from semantic3d.baselines.covariance.persistence import save_model
        from semantic3d.baselines.covariance.training import (
            find_labelled_scans,
            scan_training_rows,
            train_covariance_model,
        )

        config = _config(config_path, seed)
        if grid_search:
            config = dataclasses.replace(
                config, grid_search=dataclasses.replace(config.grid_search, select_forest=True)
            )
        labelled = find_labelled_scans(data, names=scan_names(scans))
        with open_cluster(scheduler, workers) as cluster, progress_bar() as bar:
            task = bar.add_task("features of training points", total=len(labelled))
            hooks: dict[str, Any] = {}
            if cluster is not None:  # the same rows, described by the workers
                from semantic3d.scale.training import ClusterRowsOfScan

                hooks = {
                    "map_scans": cluster.map,
                    "rows_of_scan": ClusterRowsOfScan(config, cluster, workdir=workdir),
                }
            elif workdir is not None:
                hooks = {
                    "rows_of_scan": partial(scan_training_rows, config=config, workdir=workdir)
                }
            model = train_covariance_model(
                labelled,
                config=config,
                progress=lambda _stage, done, total: bar.update(task, completed=done, total=total),
                **hooks,
            )
        save_model(model, out)
        if model.grid_search is not None:
            ui.console.print(
                f"grid search ({model.grid_search.scoring}, {model.grid_search.n_splits} folds "
                f"grouped by scan) chose {escape(str(model.grid_search.best_params))} "
                f"({model.grid_search.best_score:.4f})",
                highlight=False,
            )
        counts = ", ".join(f"{v}: {n}" for v, n in sorted(model.n_training_points.items()))
        ui.console.print(
            f"trained on {plural(len(labelled), 'scan')} ({counts} points per label value) in "
            f"{model.training_time_s:.1f} s; {len(model.feature_names)} features; saved {out}"
        )


@covariance_app.command()
def predict(
    scan: Path | None = scan_argument(),
    model_path: Path = typer.Option(..., "--model", help="Model file from `train`."),
    data: Path | None = data_option(),
    out: Path | None = out_option(),
    challenge: ChallengeChoice | None = challenge_option(),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    parallel_scans: int | None = typer.Option(
        None,
        "--parallel-scans",
        min=1,
        help="Scans labelled at a time on threads of this process (same labels; memory of "
        "that many scans; at most --threads). Default for a folder: one per 4 threads, at "
        "least 2; 1 on a Dask cluster or where numba has no thread-safe threading layer "
        "(TBB or OpenMP).",
    ),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    threads: int | None = threads_option(),
) -> None:
    """Label scans with a trained model: one SCAN, or every scan of --data.

    Writes NAME.labels and a NAME.labels.json run record (run time, hardware) per scan into
    ./predictions (or --out), never beside the scan, whose NAME.labels is usually its
    ground truth. `semantic3d evaluate --pred FOLDER` reads the folder as it is. An --out
    ending in .zip gets only the .labels files (a submission) and ZIP.json the run records.
    Existing outputs are refused unless --overwrite; Ctrl-C leaves only complete files.
    """
    with guarded():
        scans, target = scans_and_target(scan, data, out, challenge)
        _predict(
            scans,
            target,
            model_path,
            workdir=workdir,
            overwrite=overwrite,
            challenge=None if challenge is None else challenge.value,
            cluster_options=(scheduler, workers),
            parallel_scans=parallel_scans,
        )


def _predict(
    scans: tuple[ScanToLabel, ...],
    target: Path,
    model_path: Path,
    *,
    workdir: Path | None,
    overwrite: bool,
    challenge: str | None,
    cluster_options: tuple[str | None, int | None] = (None, None),
    parallel_scans: int | None = None,
) -> None:
    from semantic3d.baselines.common.prediction import parallel_scans_limit, scans_at_once
    from semantic3d.baselines.common.submission import (
        is_zip_output,
        refuse_unsafe_outputs,
    )
    from semantic3d.baselines.covariance.persistence import load_model
    from semantic3d.baselines.covariance.predict import predict_scans

    refuse_unsafe_outputs(target, scans, overwrite=overwrite)
    model = load_model(model_path)
    on_cluster = cluster_options != (None, None)
    if parallel_scans is None:  # where it is safe and helps: a scan per 4 threads, 2 or more
        parallel_scans = scans_at_once(len(scans)) if not on_cluster else 1
    elif parallel_scans > 1 and (on_cluster or parallel_scans_limit(model) == 1):
        why = (
            "the cluster labels each scan's tiles in parallel"
            if on_cluster
            else "numba's threading layer here is not thread-safe: install tbb"
        )
        ui.console.print(f"--parallel-scans: labelling one scan at a time ({why})")
    with open_cluster(*cluster_options) as cluster, progress_bar() as bar:
        task, update = scans_progress(bar, scans)

        predictor: Predictor = model
        if cluster is not None:  # tiles labelled by the workers (same labels)
            from semantic3d.scale.predict import ClusterPredictor

            predictor = ClusterPredictor(model, cluster)
        result = predict_scans(
            predictor,
            scans,
            target,
            workdir=workdir,
            progress=update,
            overwrite=overwrite,
            parallel_scans=parallel_scans,
        )
        bar.update(task, completed=result.n_points, total=result.n_points)
    print_runs(result, zipped=is_zip_output(target), challenge=challenge)


@covariance_app.command()
def cv(
    data: Path = typer.Option(..., "--data", help="Folder of NAME.txt + NAME.labels scans."),
    scans: list[str] = typer.Option([], "--scans", help=SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    seed: int | None = typer.Option(
        None, "--seed", help="Override the seed of the sampling section."
    ),
    out: Path | None = typer.Option(None, "--out", help="Write the scores as JSON here."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Grid search of forest parameters, cross-validated with folds grouped by scan."""
    with guarded():
        from rich.table import Table

        from semantic3d.baselines.common.submission import write_atomic_text

        refuse_existing([out] if out is not None else [], overwrite=overwrite)
        from semantic3d.baselines.covariance.training import (
            build_training_set,
            find_labelled_scans,
            run_grid_search,
        )

        config = _config(config_path, seed)
        labelled = find_labelled_scans(data, names=scan_names(scans))
        with progress_bar() as bar:
            task = bar.add_task("features of training points", total=len(labelled))
            training = build_training_set(
                labelled,
                config=config,
                progress=lambda _stage, done, total: bar.update(task, completed=done, total=total),
            )
        ui.console.print(f"grid search on {training.labels.size} points ...")
        result = run_grid_search(training, config=config)
        table = Table(title=f"{result.scoring}, {result.n_splits} folds grouped by scan")
        for column in ("n_estimators", "max_depth", "min_samples_leaf", "max_features"):
            table.add_column(column, justify="right")
        table.add_column("score", justify="right")
        table.add_column("± std", justify="right")
        table.add_column("fit s", justify="right")
        order = sorted(range(len(result.params)), key=lambda i: -result.mean_scores[i])
        for i in order:
            params = result.params[i]
            table.add_row(
                *(str(params[c]) for c in ("n_estimators", "max_depth", "min_samples_leaf")),
                str(params["max_features"]),
                f"{result.mean_scores[i]:.4f}",
                f"{result.std_scores[i]:.4f}",
                f"{result.fit_time_s[i]:.1f}",
            )
        ui.console.print(table)
        ui.console.print(f"best: {result.best_params} ({result.best_score:.4f})")
        if out is not None:
            write_atomic_text(
                out,
                json.dumps(
                    {
                        "scoring": result.scoring,
                        "n_splits": result.n_splits,
                        "scans": list(training.scan_names),
                        "best_params": result.best_params,
                        "best_score": result.best_score,
                        "results": [
                            {**p, "mean": _finite(m), "std": _finite(s)}
                            for p, m, s in zip(
                                result.params, result.mean_scores, result.std_scores, strict=True
                            )
                        ],
                    },
                    indent=2,
                )
                + "\n",
            )


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def register(app: typer.Typer) -> None:
    """Add the ``baseline`` command group to ``app``."""
    from semantic3d.cli.baseline_cnn import cnn_app
    from semantic3d.cli.baseline_image import image_app
    from semantic3d.cli.baseline_randla import randla_app

    baseline_app.add_typer(cnn_app, name="cnn")
    baseline_app.add_typer(image_app, name="image")
    baseline_app.add_typer(randla_app, name="randla")
    app.add_typer(baseline_app, name="baseline")
