"""``semantic3d cubemap SCAN --out DIR``: the six cube faces of a scan seen from its station.

A thin shell over :mod:`semantic3d.viz.cubemap`: resolve the station (option, simulator
sidecar, or estimate), render with a progress bar, write the PNG faces, the index faces
and a JSON description.
"""

from __future__ import annotations

from pathlib import Path

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import escape, guarded, progress_bar, refuse_existing, threads_option


def cubemap_command(
    scan: Path = typer.Argument(..., help="Scan to render (any format io reads)."),
    out: Path = typer.Option(..., "--out", help="Folder for the faces (created if needed)."),
    station: str | None = typer.Option(
        None,
        "--station",
        help="Scanner position x,y,z in metres; default the simulator's sidecar beside the "
        "scan, else an estimate from the points.",
    ),
    size: int = typer.Option(2048, "--size", help="Face edge in pixels."),
    splat_radius: int = typer.Option(
        1, "--splat-radius", help="Pixels each point also covers around its own (0..16)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace faces already in OUT."),
    threads: int | None = threads_option(),
) -> None:
    """Render a scan's colour, label and index cube faces from its station (PNG + .npy)."""
    with guarded():
        from semantic3d.io.formats import estimate_point_count, iter_points
        from semantic3d.viz.cubemap import render_cubemap, validate_size
        from semantic3d.viz.cubemap_files import cubemap_outputs, write_cubemap
        from semantic3d.viz.station import parse_station, resolve_station

        position = parse_station(station) if station is not None else None
        validate_size(size)
        if not scan.exists():
            raise FileNotFoundError(2, "No such file or directory", str(scan))
        refuse_existing(cubemap_outputs(out), overwrite=overwrite)
        resolved = resolve_station(scan, station=position)
        total = estimate_point_count(scan).n_points
        with progress_bar() as bar:
            task = bar.add_task(f"rendering {scan.name}", total=total or None)
            cubemap = render_cubemap(
                iter_points(scan),
                station=resolved.position,
                size=size,
                splat_radius_px=splat_radius,
                progress=lambda done: bar.update(task, completed=done, total=max(total, done)),
            )
        write_cubemap(cubemap, out, overwrite=overwrite)
    x, y, z = resolved.position
    ui.console.print(
        f"{cubemap.n_points:,} points from station ({x:.2f}, {y:.2f}, {z:.2f}) "
        f"{escape(f'[{resolved.source}]')}, {size}² faces, {cubemap.coverage():.0%} of pixels covered "
        f"-> {escape(str(out))}",
        highlight=False,
        soft_wrap=True,
    )


def register(app: typer.Typer) -> None:
    """Add ``cubemap`` to ``app``."""
    app.command("cubemap")(cubemap_command)
