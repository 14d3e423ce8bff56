"""``semantic3d label`` and ``semantic3d view``: the browser labelling tool and viewer."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import guarded

_PORT = typer.Option(8765, "--port", help="Port to listen on (loopback only).")
_HOST = typer.Option(
    "127.0.0.1", "--host", help="Loopback address to listen on: 127.0.0.1, ::1 or localhost."
)
_CACHE_DIR = typer.Option(
    None,
    "--cache-dir",
    help="Folder for the scan's cache and level of detail (default: $SEMANTIC3D_CACHE_DIR "
    "or the per-user cache folder); nothing is written beside the scan.",
)
_LOOPBACK = {"127.0.0.1": "127.0.0.1", "localhost": "127.0.0.1", "::1": "::1", "[::1]": "::1"}


def _check_port(host: str, port: int) -> str:
    """The loopback address to bind; one error line when ``host`` is not loopback or busy."""
    from semantic3d.labelling.errors import OperationError

    address = _LOOPBACK.get(host)
    if address is None:
        raise OperationError(
            f"--host: expected a loopback address (127.0.0.1, ::1, localhost), found {host!r}; "
            "the labelling app is for this machine only"
        )
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((address, port))
        except OSError as exc:
            raise OperationError(
                f"port {port} on {address}: cannot listen ({exc.strerror}); pass --port"
            ) from None
    return address


def _open(scan: Path, **options: Any) -> Any:
    from semantic3d.core.errors import require

    require("fastapi", "label")
    require("uvicorn", "label")
    from semantic3d.cli.console import progress_bar
    from semantic3d.labelling.opening import open_label_session

    stages = {
        "cache": "caching the scan",
        "bounds": "level of detail: bounds",
        "histogram": "level of detail: cells",
        "refine": "level of detail: dense cells",
        "counts": "level of detail: nodes",
        "write": "level of detail: writing",
    }
    with progress_bar() as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stages.get(stage, stage), total=total or None)
            bar.update(tasks[stage], completed=done, total=total or None)

        return open_label_session(scan, progress=progress, **options)


def _serve(session: Any, address: str, port: int, what: str) -> None:
    import uvicorn

    from semantic3d.labelling.app import create_label_app

    app = create_label_app(session, port=port)
    shown = f"[{address}]" if ":" in address else address
    url = f"http://{shown}:{port}/?token={app.state.secret}"
    ui.console.print(f"{what} {session.scan.path.name} ({session.n_points:,} points) at")
    ui.console.print(url, soft_wrap=True, markup=False, highlight=False)
    ui.console.print("open that address (it holds this launch's secret); press Ctrl+C to stop")
    try:
        uvicorn.run(app, host=address, port=port, log_level="warning")
    finally:
        session.close()


def label(
    scan: Path = typer.Argument(..., help="Scan: .txt/.las/.laz/.ply or a cache folder."),
    labels: Path | None = typer.Option(
        None,
        "--labels",
        help="Labels file to write (default: NAME.labels beside the scan when it has none, "
        "else NAME.edit.labels starting from NAME.labels). An existing file is resumed when "
        "an earlier labelling session wrote it, else refused without --overwrite.",
    ),
    start_from: Path | None = typer.Option(
        None,
        "--from",
        help="Labels to start from, read-only (default: the scan's NAME.labels, if any).",
    ),
    overwrite: bool = typer.Option(
        False, "--overwrite", help="Edit an existing labels file in place (e.g. a ground truth)."
    ),
    cache_dir: Path | None = _CACHE_DIR,
    port: int = _PORT,
    host: str = _HOST,
) -> None:
    """Label a scan in the browser (2D polygon and 3D model-fitting workflows)."""
    with guarded():
        from semantic3d.labelling.opening import plan_labels

        address = _check_port(host, port)
        plan = plan_labels(scan, labels=labels, start_from=start_from, overwrite=overwrite)
        ui.console.print(
            f"labels: {plan.describe()}", markup=False, highlight=False, soft_wrap=True
        )
        session = _open(
            scan,
            labels_path=plan.output,
            start_from=plan.start_from,
            overwrite=overwrite,
            cache_dir=cache_dir,
        )
        _serve(session, address, port, "labelling")


def view(
    scan: Path = typer.Argument(..., help="Scan: .txt/.las/.laz/.ply or a cache folder."),
    labels: Path | None = typer.Option(None, "--labels", help="Ground-truth .labels file."),
    pred: Path | None = typer.Option(None, "--pred", help="Predicted .labels file."),
    cache_dir: Path | None = _CACHE_DIR,
    port: int = _PORT,
    host: str = _HOST,
) -> None:
    """View a scan, its labels and a prediction (with its errors) in the browser, read-only."""
    with guarded():
        address = _check_port(host, port)
        session = _open(
            scan, labels_path=labels, prediction_path=pred, read_only=True, cache_dir=cache_dir
        )
        _serve(session, address, port, "viewing")


def register(app: typer.Typer) -> None:
    """Add ``label`` and ``view`` to ``app``."""
    app.command("label")(label)
    app.command("view")(view)
