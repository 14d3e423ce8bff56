"""Benchmark server commands: ``serve``, ``worker``, ``submit`` and the ``admin`` group.

Server-side commands read their settings from ``SEMANTIC3D_*`` environment variables
(``--data-dir`` and ``--database-url`` override the two that matter most).
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import MARKUP_MODE, guarded, plural, progress_bar

_DATA_DIR = typer.Option(
    None, "--data-dir", help="Data folder (default: $SEMANTIC3D_DATA_DIR, else ./semantic3d-data)."
)
_DATABASE_URL = typer.Option(
    None,
    "--database-url",
    help="SQLAlchemy URL, e.g. postgresql+psycopg://user@host/db "
    "(default: $SEMANTIC3D_DATABASE_URL, else SQLite in the data folder).",
)


def _settings(data_dir: Path | None, database_url: str | None, **extra: Any) -> Any:
    from semantic3d.core.errors import require

    # what the settings need (fastapi, 0.6 s to import here, only for serving)
    require("pydantic_settings", "server")
    from semantic3d.server.settings import load_settings

    overrides = dict(extra)
    if data_dir is not None:
        overrides["data_dir"] = data_dir
    if database_url is not None:
        overrides["database_url"] = database_url
    return load_settings(**overrides)


def _database(settings: Any) -> Any:
    from semantic3d.server.db import create_db_engine, create_session_factory, run_migrations

    engine = create_db_engine(settings)
    run_migrations(engine)
    return create_session_factory(engine)


def serve(
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
    port: int = typer.Option(8000, "--port", help="Port to listen on."),
    worker: bool | None = typer.Option(
        None,
        "--worker/--no-worker",
        help="Run the evaluation worker in this process (default: yes with SQLite, "
        "no with PostgreSQL: run `semantic3d worker` beside it).",
    ),
    data_dir: Path | None = _DATA_DIR,
    database_url: str | None = _DATABASE_URL,
    proxy_headers: bool | None = typer.Option(
        None,
        "--proxy-headers/--no-proxy-headers",
        help="Behind a reverse proxy: client addresses from X-Forwarded-For, believed only "
        "from $SEMANTIC3D_FORWARDED_ALLOW_IPS (default 127.0.0.1,::1).",
    ),
) -> None:
    """Run the benchmark server (web pages and API) with uvicorn."""
    with guarded():
        from semantic3d.core.errors import require

        require("fastapi", "server")
        require("uvicorn", "server")
        from semantic3d.server.serving import bind_listener

        extra: dict[str, Any] = {} if worker is None else {"embedded_worker": worker}
        if proxy_headers is not None:
            extra["proxy_headers"] = proxy_headers
        settings = _settings(data_dir, database_url, **extra)
        sock = bind_listener(host, port)  # a busy port is one line, before any work
        from semantic3d.server.app import create_app
        from semantic3d.server.serving import run_server

        app = create_app(settings)
        ui.err_console.print(
            f"semantic3d server on http://{host}:{port} · data {settings.data_dir}"
            + (" · embedded worker" if settings.runs_embedded_worker else "")
        )
        run_server(app, settings, sock)


def worker(
    once: bool = typer.Option(False, "--once", help="Process at most one job, then exit."),
    data_dir: Path | None = _DATA_DIR,
    database_url: str | None = _DATABASE_URL,
) -> None:
    """Evaluate queued submissions until interrupted (run as many as you like)."""
    with guarded():
        from semantic3d.server.worker import Worker

        settings = _settings(data_dir, database_url)
        runner = Worker(settings, _database(settings))
        if once:
            worked = runner.run_once()
            ui.console.print("evaluated one submission" if worked else "queue empty")
            return
        stop = threading.Event()

        def _stop(signum: int, frame: object) -> None:
            ui.err_console.print("stopping: a running job is handed back to the queue")
            stop.set()

        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
        ui.err_console.print(f"worker {runner.worker_id} on {settings.data_dir}")
        runner.run(stop)


def submit(
    predictions: Path = typer.Argument(
        ..., exists=True, dir_okay=False, help="Zip of .labels files."
    ),
    server: str = typer.Option(..., "--server", envvar="SEMANTIC3D_SERVER", help="Server URL."),
    challenge: str = typer.Option(..., "--challenge", help="Challenge name, e.g. reduced-8."),
    token: str = typer.Option(
        ..., "--token", envvar="SEMANTIC3D_TOKEN", help="API token from your account page."
    ),
    method: str = typer.Option(..., "--method", help="Method name for the leaderboard."),
    description: str = typer.Option("", "--description", help="Method description."),
    paper_url: str = typer.Option("", "--paper-url", help="Link to the paper (http/https)."),
    code_url: str = typer.Option("", "--code-url", help="Link to the code (http/https)."),
    runtime_s: float | None = typer.Option(None, "--runtime-s", help="Run time T in seconds."),
    hardware: str | None = typer.Option(None, "--hardware", help="e.g. '1x A100, 32 cores'."),
    wait: bool = typer.Option(False, "--wait", help="Wait for the evaluation and show scores."),
    publish: bool = typer.Option(
        False, "--publish", help="Publish once evaluated (implies --wait)."
    ),
    chunk_mib: int = typer.Option(64, "--chunk-mib", min=1, help="Upload chunk size in MiB."),
) -> None:
    """Upload a submission (chunked, resumable: run again to continue) and queue it."""
    with guarded():
        from semantic3d.core.errors import require

        require("httpx", "server")
        from semantic3d.evaluation.result import MethodInfo
        from semantic3d.server.client import BenchmarkClient, file_sha256

        info = MethodInfo(
            name=method,
            runtime_s=runtime_s,
            hardware=hardware,
            description=description,
            paper_url=paper_url,
            code_url=code_url,
        )
        size = predictions.stat().st_size
        with BenchmarkClient(server, token) as client, progress_bar(bytes_=True) as bar:
            task = bar.add_task("hashing", total=size)
            digest = file_sha256(predictions, progress=lambda d, t: bar.update(task, completed=d))
            bar.update(task, description="uploading", completed=0)
            upload_id = client.upload(
                predictions,
                challenge=challenge,
                chunk_bytes=chunk_mib << 20,
                sha256=digest,
                progress=lambda d, t: bar.update(task, completed=d),
            )
            bar.update(task, description="validating", completed=size)
            submission_id = client.finalize(upload_id, method=info, source=predictions.name).id
            ui.console.print(
                f"submission #{submission_id} queued: {client.server}/submissions/{submission_id}"
            )
            if not (wait or publish):
                return
            eval_task = bar.add_task("evaluating", total=None)
            final = client.wait(
                submission_id,
                progress=lambda d, t: bar.update(eval_task, completed=d, total=t),
            )
        from semantic3d.server.client import ClientError

        if final.status == "failed" or final.scores is None:
            raise ClientError(f"submission #{submission_id} failed: {final.error}")
        scores = final.scores
        ui.console.print(
            f"mIoU {_percent(scores.mean_iou)} · OA {_percent(scores.overall_accuracy)} "
            f"({scores.n_points:,} points)"
        )
        if publish:
            with BenchmarkClient(server, token) as client:
                client.publish(submission_id)
            ui.console.print(f"published on {server.rstrip('/')}/challenges/{challenge}")


def _percent(fraction: float | None) -> str:
    """A score for people: per cent with one decimal, ``–`` when unknown."""
    return "–" if fraction is None else f"{100 * fraction:.1f}"


admin_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="Administer a benchmark server (run where its data dir / database is).",
    no_args_is_help=True,
)


@admin_app.command("add-challenge")
def add_challenge(
    name: str = typer.Argument(
        ..., help="semantic-8, reduced-8 (the benchmark's) or a name for a custom challenge."
    ),
    ground_truth: Path = typer.Option(
        ..., "--ground-truth", exists=True, file_okay=False, help="Folder of .labels files."
    ),
    link: bool = typer.Option(
        False, "--link", help="Symlink the files instead of copying them under the data dir."
    ),
    title: str | None = typer.Option(None, "--title", help="Shown on the pages (default: NAME)."),
    description: str = typer.Option("", "--description", help="Shown above the leaderboard."),
    data_dir: Path | None = _DATA_DIR,
    database_url: str | None = _DATABASE_URL,
) -> None:
    """Install a challenge's hidden ground truth (checked and counted once)."""
    with guarded():
        from semantic3d.server.services.challenges import install_challenge

        settings = _settings(data_dir, database_url)
        row = install_challenge(
            _database(settings),
            settings,
            name,
            ground_truth,
            link=link,
            title=title,
            description=description,
        )
        ui.console.print(
            f"challenge {row.name}: {plural(row.n_scans, 'scan')}, "
            f"{plural(row.n_points or 0, 'point')} installed"
        )


@admin_app.command("create-user")
def create_user(
    username: str = typer.Argument(..., help="3-32 characters: a-z, 0-9, '_', '.', '-'."),
    password: str = typer.Option(
        ...,
        "--password",
        help="At least 8 characters; prompted for (hidden) when not given.",
        envvar="SEMANTIC3D_NEW_PASSWORD",
        prompt=True,
        hide_input=True,
        confirmation_prompt=True,
    ),
    admin: bool = typer.Option(False, "--admin", help="Give the account the admin role."),
    data_dir: Path | None = _DATA_DIR,
    database_url: str | None = _DATABASE_URL,
) -> None:
    """Create an account (--admin for an administrator; the password is prompted for)."""
    with guarded():
        from semantic3d.server.services.accounts import create_user as create

        settings = _settings(data_dir, database_url)
        user = create(_database(settings), username, password, is_admin=admin)
        ui.console.print(f"account {user.username} created" + (" (admin)" if admin else ""))


@admin_app.command("set-admin")
def set_admin(
    username: str = typer.Argument(..., help="An existing account."),
    revoke: bool = typer.Option(False, "--revoke", help="Take the admin role away instead."),
    data_dir: Path | None = _DATA_DIR,
    database_url: str | None = _DATABASE_URL,
) -> None:
    """Give an existing account the admin role (or take it away with --revoke)."""
    with guarded():
        from semantic3d.server.services.accounts import set_admin as update

        settings = _settings(data_dir, database_url)
        user = update(_database(settings), username, is_admin=not revoke)
        ui.console.print(
            f"account {user.username} is {'now' if user.is_admin else 'no longer'} an admin"
        )


@admin_app.command("create-token")
def create_token(
    username: str = typer.Argument(..., help="The account the token acts for."),
    name: str = typer.Option("cli", "--name", help="Label shown on the account page."),
    data_dir: Path | None = _DATA_DIR,
    database_url: str | None = _DATABASE_URL,
) -> None:
    """Create an API token for an account and print it (shown only this once)."""
    with guarded():
        from semantic3d.server.services.accounts import create_token_for

        settings = _settings(data_dir, database_url)
        typer.echo(create_token_for(_database(settings), username, name))


@admin_app.command("list-challenges")
def list_challenges(
    data_dir: Path | None = _DATA_DIR, database_url: str | None = _DATABASE_URL
) -> None:
    """List installed challenges."""
    with guarded():
        from semantic3d.server.services.challenges import list_challenges as rows

        settings = _settings(data_dir, database_url)
        for row in rows(_database(settings)):
            state = "open" if row.is_open else "closed"
            typer.echo(f"{row.name}\t{row.kind}\t{plural(row.n_scans, 'scan')}\t{state}")


def serve_demo(
    out: Path,
    *,
    result: Any,
    ground_truth: Path,
    port: int = 8000,
    host: str = "127.0.0.1",
    predictions: Path | None = None,
) -> None:
    """``semantic3d demo --serve``: a server on ``out/server-data`` showing the demo's result.

    ``result`` is the demo's own :class:`~semantic3d.evaluation.EvaluationResult`; the
    server scores the demo's submission (``out/submission``, the ``.labels`` files named as
    the ground truth's) itself and the two must agree.
    """
    with guarded():
        from semantic3d.evaluation import MethodInfo
        from semantic3d.server.app import create_app
        from semantic3d.server.demo import prepare_demo
        from semantic3d.server.serving import bind_listener, run_server

        settings = _settings(
            out / "server-data", None, submission_cooldown_h=0, embedded_worker=True
        )
        sock = bind_listener(host, port)
        method = result.method or MethodInfo(name="demo baseline")
        demo = prepare_demo(
            _database(settings),
            settings,
            ground_truth=ground_truth,
            predictions=predictions or out / "submission",
            method=method,
        )
        if demo.mean_iou is None or abs(demo.mean_iou - result.scores.mean_iou) > 1e-12:
            ui.err_console.print(
                f"[yellow]warning:[/] the server scored mIoU {demo.mean_iou}, "
                f"the demo {result.scores.mean_iou}"
            )
        url = f"http://{host}:{port}"
        ui.console.rule("5. benchmark server")
        ui.console.print(f"leaderboard  {url}/challenges/demo")
        ui.console.print(f"method page  {url}/submissions/{demo.submission_id}")
        if demo.password is not None:
            ui.console.print(f"account      demo / {demo.password}")
            ui.console.print(f"API token    {demo.token}")
        ui.console.print("[dim]Ctrl-C stops the server[/]")
        run_server(create_app(settings), settings, sock, log_level="warning")


def register(app: typer.Typer) -> None:
    """Add ``serve``, ``worker``, ``submit`` and ``admin`` to ``app``."""
    app.command("serve")(serve)
    app.command("worker")(worker)
    app.command("submit")(submit)
    app.add_typer(admin_app, name="admin")


def _main() -> None:
    """``python -m semantic3d.cli.server``: these commands alone (used by the tests)."""
    import logging

    from semantic3d.cli.console import run_guarded

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    app = typer.Typer(
        rich_markup_mode=MARKUP_MODE, add_completion=False, pretty_exceptions_enable=False
    )
    register(app)
    run_guarded(app)


if __name__ == "__main__":
    _main()
