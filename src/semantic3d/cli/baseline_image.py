"""``semantic3d baseline image train | predict``: the paper's 2D image baseline.

Thin shells over :mod:`semantic3d.baselines.image`: parse arguments, call the library
with a progress bar, print a summary. scikit-learn, scikit-image and torch are imported
when a command runs.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import (
    MARKUP_MODE,
    escape,
    fail,
    guarded,
    plural,
    progress_bar,
    refuse_existing,
    threads_option,
)

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

image_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="2D image baseline: cube maps of each station, image segmentation, labels back to points.",
    no_args_is_help=True,
)

_OVERWRITE_HELP = "Replace outputs that already exist (refused otherwise)."


class VariantChoice(StrEnum):
    """Segmenters ``train`` can fit."""

    BOOSTED = "boosted"
    UNET = "unet"


def _scan_names(scans: list[str]) -> list[str]:
    return [name.strip() for item in scans for name in item.split(",") if name.strip()]


@image_app.command()
def train(
    data: Path = typer.Option(
        ..., "--data", help="Folder of labelled scans (NAME.txt + NAME.labels)."
    ),
    out: Path = typer.Option(..., "--out", help="Model file to write."),
    scans: list[str] = typer.Option([], "--scans", help="Scan names to use; default all."),
    variant: VariantChoice = typer.Option(
        VariantChoice.BOOSTED, "--variant", help="boosted (the paper's) or unet ([torch])."
    ),
    config_path: Path | None = typer.Option(
        None, "--config", help='TOML configuration (preset = "paper" or "small", sections).'
    ),
    preset: str | None = typer.Option(None, "--preset", help="paper or small (without --config)."),
    seed: int | None = typer.Option(None, "--seed", help="Override the configuration's seed."),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Render the labelled scans' cube maps from their stations and train a segmenter."""
    with guarded():
        refuse_existing([out], overwrite=overwrite)
        from semantic3d.baselines.common.scans import find_labelled_scans
        from semantic3d.baselines.image.config import load_config, preset_config, with_seed
        from semantic3d.baselines.image.model import ImageVariant
        from semantic3d.baselines.image.persistence import save_model
        from semantic3d.baselines.image.training import train_image_model

        if config_path is not None and preset is not None:
            raise fail("expected --config or --preset, found both")
        config = load_config(config_path) if config_path else preset_config(preset or "paper")
        config = with_seed(config, seed)
        labelled = find_labelled_scans(data, names=_scan_names(scans))
        with progress_bar() as bar:
            task = bar.add_task("rendering", total=len(labelled))

            def update(stage: str, done: int, total: int) -> None:
                bar.update(task, description=stage, completed=done, total=total)

            model = train_image_model(
                labelled, config=config, variant=ImageVariant(variant.value), progress=update
            )
        save_model(model, out)
        ui.console.print(
            f"{model.variant.value} model trained on {plural(len(labelled), 'scan')} "
            f"(label values {list(model.label_values)}) in {model.training_time_s:.1f} s; "
            f"saved {escape(str(out))}",
            highlight=False,
            soft_wrap=True,
        )


@image_app.command()
def predict(
    scans: list[Path] = typer.Argument(..., help="Scans to label (any format)."),
    model_path: Path = typer.Option(..., "--model", help="Model file from `train`."),
    out: Path = typer.Option(
        Path("predictions"), "--out", help="Folder for NAME.labels, NAME.labels.json, NAME.faces/."
    ),
    station: str | None = typer.Option(
        None,
        "--station",
        help="Scanner position x,y,z (one scan only); default the simulator's sidecar, "
        "else estimated.",
    ),
    no_faces: bool = typer.Option(False, "--no-faces", help="Skip the face pictures."),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder."),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Label scans: NAME.labels + run record, and NAME.faces/ (colour | truth | prediction)."""
    with guarded():
        from semantic3d.viz.station import parse_station

        position = parse_station(station) if station is not None else None
        if position is not None and len(scans) > 1:
            raise fail(f"--station applies to one scan, found {len(scans)}")
        missing = [scan for scan in scans if not scan.exists()]
        if missing:
            raise fail(f"{missing[0]}: expected a scan file, found none")
        from semantic3d.baselines.common.submission import refuse_existing_outputs
        from semantic3d.baselines.image.persistence import load_model
        from semantic3d.baselines.image.predict import predict_image_scan, prediction_outputs

        targets = [out / f"{scan.stem}.labels" for scan in scans]
        refuse_existing_outputs(
            [p for t in targets for p in prediction_outputs(t, with_faces=not no_faces)],
            overwrite=overwrite,
        )
        model = load_model(model_path)
        for scan, target in zip(scans, targets, strict=True):
            with progress_bar() as bar:
                task = bar.add_task(f"labelling {scan.name}", total=None)

                def update(done: int, total: int, task: TaskID = task, bar: Progress = bar) -> None:
                    bar.update(task, completed=done, total=total or None)

                result = predict_image_scan(
                    model,
                    scan,
                    out_path=target,
                    station=position,
                    write_faces=not no_faces,
                    workdir=workdir,
                    progress=update,
                    overwrite=overwrite,
                )
            x, y, z = result.station.position
            ui.console.print(
                f"{escape(scan.name)}: {plural(result.run.n_points, 'point')} in "
                f"{result.run.runtime_s:.1f} s ({result.run.points_per_second:,.0f} points/s), "
                f"station ({x:.2f}, {y:.2f}, {z:.2f}) {escape(f'[{result.station.source}]')} "
                f"-> {escape(result.run.labels_path)}",
                highlight=False,
                soft_wrap=True,
            )
