"""``semantic3d baseline image train | predict``: the paper's 2D image baseline.

Thin shells over :mod:`semantic3d.baselines.image`: parse arguments, call the library
with a progress bar, print a summary. scikit-learn, scikit-image and torch are imported
when a command runs.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.baseline_common import (
    OVERWRITE_HELP,
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

image_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="2D image baseline: cube maps of each station, image segmentation, labels back to points.",
    no_args_is_help=True,
)


class VariantChoice(StrEnum):
    """Segmenters ``train`` can fit."""

    BOOSTED = "boosted"
    UNET = "unet"


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
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
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
        labelled = find_labelled_scans(data, names=scan_names(scans))
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
    scan: Path | None = scan_argument(),
    model_path: Path = typer.Option(..., "--model", help="Model file from `train`."),
    data: Path | None = data_option(),
    out: Path | None = out_option(),
    challenge: ChallengeChoice | None = challenge_option(),
    station: str | None = typer.Option(
        None,
        "--station",
        help="Scanner position x,y,z (one scan only); default the simulator's sidecar, "
        "else estimated.",
    ),
    faces: Path | None = typer.Option(
        None,
        "--faces",
        file_okay=False,
        help="Also write each scan's face pictures (colour | truth | prediction) into FACES/NAME/.",
    ),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Label scans with a trained model: one SCAN, or every scan of --data.

    Writes NAME.labels and a NAME.labels.json run record per scan into ./predictions (or
    --out: a folder, a .zip ready for `submit`, or for one scan a .labels file), as every
    baseline's predict does; the face pictures only with --faces.
    """
    with guarded():
        from semantic3d.viz.station import parse_station

        position = parse_station(station) if station is not None else None
        scans_to_label, target = scans_and_target(scan, data, out, challenge)
        if position is not None and len(scans_to_label) > 1:
            raise fail(f"--station applies to one scan, found {len(scans_to_label)}")
        from semantic3d.baselines.common.submission import is_zip_output, refuse_unsafe_outputs
        from semantic3d.baselines.image.persistence import load_model
        from semantic3d.baselines.image.predict import predict_image_scans

        refuse_unsafe_outputs(target, scans_to_label, overwrite=overwrite)
        model = load_model(model_path)
        with progress_bar() as bar:
            _, update = scans_progress(bar, scans_to_label)

            result = predict_image_scans(
                model,
                scans_to_label,
                target,
                station=position,
                faces_dir=faces,
                workdir=workdir,
                progress=update,
                overwrite=overwrite,
            )
        for scanned in result.scans:
            x, y, z = scanned.station.position
            where = f"; faces in {scanned.faces_dir}" if scanned.faces_dir is not None else ""
            ui.console.print(
                f"{escape(Path(scanned.run.scan).name)}: station ({x:.2f}, {y:.2f}, {z:.2f}) "
                f"{escape(f'[{scanned.station.source}]')}{escape(where)}",
                highlight=False,
                soft_wrap=True,
            )
        print_runs(
            result.runs,
            zipped=is_zip_output(target),
            challenge=None if challenge is None else challenge.value,
        )
