"""``semantic3d simulate``: labelled terrestrial laser scans of procedural scenes.

A thin shell over :func:`semantic3d.datasets.simulator.simulate`: it checks the arguments
(through the library's validators, so errors read the same), shows progress and prints a
summary of what was written.
"""

from __future__ import annotations

from pathlib import Path

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.cluster import open_cluster, scheduler_option, workers_option
from semantic3d.cli.console import guarded, progress_bar, refuse_existing, threads_option

#: The simulator's scene names and station limit, repeated so that building the app does
#: not import the simulator (a test keeps them equal to ``SceneName`` / ``MAX_STATIONS``).
SCENE_NAMES = ("village", "street", "square", "railway")
MAX_STATIONS = 3
#: ``semantic3d.io.chunks.DEFAULT_CHUNK_SIZE`` (kept equal by a test).
DEFAULT_CHUNK_SIZE = 1 << 20

_SCENES = ", ".join(SCENE_NAMES)


def simulate_command(
    scene: str = typer.Option("village", "--scene", help=f"Scene to scan: {_SCENES}."),
    stations: int = typer.Option(
        1, "--stations", help=f"Stations to scan from, 1..{MAX_STATIONS}."
    ),
    points: int = typer.Option(
        1_000_000,
        "--points",
        help="About this many points per station (the step is solved for it).",
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the scene layout and the scanner noise."),
    out: Path = typer.Option(Path("simulated"), "--out", help="Output folder (created if needed)."),
    chunk_size: int = typer.Option(
        DEFAULT_CHUNK_SIZE, "--chunk-size", min=1, help="Points per streamed chunk."
    ),
    overwrite: bool = typer.Option(
        False, "--overwrite", help="Replace files of an earlier simulation in OUT."
    ),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    threads: int | None = threads_option(),
) -> None:
    """Simulate static laser scans: NAME_stationK.txt + .labels per station and NAME.json.

    With --scheduler or --workers each station is a Dask task (the same files as without).
    """
    with guarded():
        from semantic3d.datasets.simulator import simulate
        from semantic3d.datasets.simulator.scanner import validate_n_points
        from semantic3d.datasets.simulator.scenes import validate_scene_name
        from semantic3d.datasets.simulator.simulation import (
            prepare_output_folder,
            validate_stations,
        )

        scene_name = validate_scene_name(scene)
        validate_n_points(points)
        validate_stations(stations)
        stems = [f"{scene_name.value}_station{k}" for k in range(1, stations + 1)]
        refuse_existing(
            [out / f"{stem}{suffix}" for stem in stems for suffix in (".txt", ".labels")]
            + [out / f"{scene_name.value}.json"],
            overwrite=overwrite,
        )
        prepare_output_folder(out)
        with open_cluster(scheduler, workers) as cluster, progress_bar() as bar:
            if cluster is None:
                task = bar.add_task(f"scanning {scene_name.value}", total=None)

                def progress(done: int, total: int) -> None:
                    bar.update(task, completed=done, total=max(total, done))

                result = simulate(
                    scene_name,
                    out=out,
                    n_points=points,
                    stations=stations,
                    seed=seed,
                    chunk_size=chunk_size,
                    progress=progress,
                )
                bar.update(task, completed=result.n_points, total=result.n_points)
            else:
                from semantic3d.scale.simulate import simulate_on_cluster

                task = bar.add_task(f"scanning {scene_name.value} (stations)", total=stations)
                result = simulate_on_cluster(
                    scene_name,
                    out=out,
                    n_points=points,
                    cluster=cluster,
                    stations=stations,
                    seed=seed,
                    chunk_size=chunk_size,
                    progress=lambda done, total: bar.update(task, completed=done),
                )
    from rich.table import Table

    from semantic3d.core.classes import CLASSES

    table = Table(title=f"{result.scene} (seed {result.seed})", title_justify="left")
    table.add_column("station")
    table.add_column("points", justify="right")
    table.add_column("file")
    table.add_column("largest classes")
    for scan in result.scans:
        shares = sorted(
            ((scan.class_counts[c.value] / max(scan.n_points, 1), c.name) for c in CLASSES),
            reverse=True,
        )
        table.add_row(
            scan.station.name,
            f"{scan.n_points:,}",
            scan.points_path.name,
            ", ".join(f"{name} {share:.0%}" for share, name in shares[:3]),
        )
    ui.console.print(table)
    ui.console.print(f"poses and settings: {result.sidecar_path}", highlight=False, soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to ``app``."""
    app.command("simulate")(simulate_command)
