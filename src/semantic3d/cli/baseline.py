"""``semantic3d baseline covariance train | predict | cv``: the 3D covariance baseline.

Thin shells over :mod:`semantic3d.baselines.covariance`: parse arguments, call the library
with a progress bar, print a summary.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.table import Table

from semantic3d.cli.console import console, guarded, progress_bar

if TYPE_CHECKING:
    from semantic3d.baselines.covariance.config import CovarianceConfig

baseline_app = typer.Typer(
    help="Baselines: train, predict and cross-validate.", no_args_is_help=True
)
covariance_app = typer.Typer(
    help="3D covariance baseline (Hackel et al. 2016): multi-scale features + random forest.",
    no_args_is_help=True,
)
baseline_app.add_typer(covariance_app, name="covariance")

_CONFIG_HELP = (
    "TOML configuration with the sections features, forest, sampling, prediction, grid_search."
)
_SCANS_HELP = "Scan names (NAME of NAME.txt) to use, repeatable or comma-separated; default all."


def _scan_names(scans: list[str]) -> list[str]:
    return [name.strip() for item in scans for name in item.split(",") if name.strip()]


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
    scans: list[str] = typer.Option([], "--scans", help=_SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    seed: int | None = typer.Option(
        None, "--seed", help="Override the seed of the sampling section."
    ),
) -> None:
    """Train on labelled scans (class-balanced sample) and save the model."""
    with guarded():
        from semantic3d.baselines.covariance.persistence import save_model
        from semantic3d.baselines.covariance.training import (
            find_labelled_scans,
            train_covariance_model,
        )

        config = _config(config_path, seed)
        labelled = find_labelled_scans(data, names=_scan_names(scans))
        with progress_bar() as bar:
            task = bar.add_task("features of training points", total=len(labelled))
            model = train_covariance_model(
                labelled,
                config=config,
                progress=lambda _stage, done, total: bar.update(task, completed=done, total=total),
            )
        save_model(model, out)
        counts = ", ".join(f"{v}: {n}" for v, n in sorted(model.n_training_points.items()))
        console.print(
            f"trained on {len(labelled)} scans ({counts} points per label value) in "
            f"{model.training_time_s:.1f} s; {len(model.feature_names)} features; saved {out}"
        )


@covariance_app.command()
def predict(
    scan: Path = typer.Argument(..., help="Scan to label (x y z intensity r g b lines)."),
    model_path: Path = typer.Option(..., "--model", help="Model file from `train`."),
    out: Path | None = typer.Option(None, "--out", help="Labels file (default SCAN.labels)."),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
) -> None:
    """Label every point of a scan; writes LABELS and LABELS.json (run time, hardware)."""
    with guarded():
        from semantic3d.baselines.covariance.persistence import load_model
        from semantic3d.baselines.covariance.predict import predict_scan

        model = load_model(model_path)
        with progress_bar() as bar:
            task = bar.add_task(f"labelling {scan.name}", total=None)

            def update(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total or None)

            run = predict_scan(model, scan, out_path=out, workdir=workdir, progress=update)
        console.print(
            f"{run.n_points} points labelled in {run.runtime_s:.1f} s "
            f"({run.points_per_second:,.0f} points/s{', tiled' if run.tiled else ''}) "
            f"-> {run.labels_path}"
        )


@covariance_app.command()
def cv(
    data: Path = typer.Option(..., "--data", help="Folder of NAME.txt + NAME.labels scans."),
    scans: list[str] = typer.Option([], "--scans", help=_SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    seed: int | None = typer.Option(
        None, "--seed", help="Override the seed of the sampling section."
    ),
    out: Path | None = typer.Option(None, "--out", help="Write the scores as JSON here."),
) -> None:
    """Grid search of forest parameters, cross-validated with folds grouped by scan."""
    with guarded():
        from semantic3d.baselines.covariance.training import (
            build_training_set,
            find_labelled_scans,
            run_grid_search,
        )

        config = _config(config_path, seed)
        labelled = find_labelled_scans(data, names=_scan_names(scans))
        with progress_bar() as bar:
            task = bar.add_task("features of training points", total=len(labelled))
            training = build_training_set(
                labelled,
                config=config,
                progress=lambda _stage, done, total: bar.update(task, completed=done, total=total),
            )
        console.print(f"grid search on {training.labels.size} points ...")
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
        console.print(table)
        console.print(f"best: {result.best_params} ({result.best_score:.4f})")
        if out is not None:
            out.write_text(
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
                + "\n"
            )


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def register(app: typer.Typer) -> None:
    """Add the ``baseline`` command group to ``app``."""
    app.add_typer(baseline_app, name="baseline")
