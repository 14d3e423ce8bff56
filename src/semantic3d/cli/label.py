"""``semantic3d label`` and ``semantic3d view``: the browser labelling tool and viewer."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import guarded

_PORT = typer.Option(8765, "--port", help="Port to listen on (127.0.0.1 only).")
_HOST = typer.Option("127.0.0.1", "--host", help="Address to listen on.")


def _open(scan: Path, **options: Any) -> Any:
    from semantic3d.core.errors import require

    require("fastapi", "label")
    require("uvicorn", "label")
    from semantic3d.cli.console import progress_bar
    from semantic3d.labelling.session import open_label_session

    stages = {
        "cache": "caching the scan",
        "bounds": "level of detail 1/4",
        "histogram": "level of detail 2/4",
        "counts": "level of detail 3/4",
        "write": "level of detail 4/4",
    }
    with progress_bar() as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stages.get(stage, stage), total=total or None)
            bar.update(tasks[stage], completed=done, total=total or None)

        return open_label_session(scan, progress=progress, **options)


def _serve(session: Any, host: str, port: int, what: str) -> None:
    import uvicorn

    from semantic3d.labelling.app import create_label_app

    app = create_label_app(session)
    url = f"http://{host}:{port}/"
    ui.console.print(f"{what} {session.scan.path.name} ({session.n_points:,} points) at {url}")
    ui.console.print("press Ctrl+C to stop; every operation is already in the journal")
    try:
        uvicorn.run(app, host=host, port=port, log_level="warning")
    finally:
        session.close()


def label(
    scan: Path = typer.Argument(..., help="Scan: .txt/.las/.laz/.ply or a cache folder."),
    labels: Path | None = typer.Option(
        None,
        "--labels",
        help="Labels file to resume from and save to (default: NAME.labels beside the scan).",
    ),
    port: int = _PORT,
    host: str = _HOST,
) -> None:
    """Label a scan in the browser (2D polygon and 3D model-fitting workflows)."""
    with guarded():
        labels_path = labels if labels is not None else _default_labels(scan)
        session = _open(scan, labels_path=labels_path)
        _serve(session, host, port, "labelling")


def view(
    scan: Path = typer.Argument(..., help="Scan: .txt/.las/.laz/.ply or a cache folder."),
    labels: Path | None = typer.Option(None, "--labels", help="Ground-truth .labels file."),
    pred: Path | None = typer.Option(None, "--pred", help="Predicted .labels file."),
    port: int = _PORT,
    host: str = _HOST,
) -> None:
    """View a scan, its labels and a prediction (with its errors) in the browser, read-only."""
    with guarded():
        session = _open(scan, labels_path=labels, prediction_path=pred, read_only=True)
        _serve(session, host, port, "viewing")


def _default_labels(scan: Path) -> Path:
    """``NAME.labels`` beside ``NAME.txt`` (or beside the cache folder ``NAME.cache``)."""
    return scan.with_suffix(".labels")


def register(app: typer.Typer) -> None:
    """Add ``label`` and ``view`` to ``app``."""
    app.command("label")(label)
    app.command("view")(view)
