"""The server's commands through typer's CliRunner: admin group and a one-shot worker."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from semantic3d.cli import server as server_commands

from .conftest import PASSWORD


@pytest.fixture
def cli() -> typer.Typer:
    app = typer.Typer()
    server_commands.register(app)
    return app


def run(cli: typer.Typer, *args: str, input: str | None = None):
    return CliRunner().invoke(cli, list(args), input=input, catch_exceptions=False)


def test_admin_commands_set_up_a_server(
    cli: typer.Typer, tmp_path: Path, ground_truth_dir: Path
) -> None:
    data = str(tmp_path / "data")
    added = run(
        cli,
        "admin",
        "add-challenge",
        "toy",
        "--ground-truth",
        str(ground_truth_dir),
        "--data-dir",
        data,
    )
    assert added.exit_code == 0, added.output
    assert "2 scans, 5,000 points" in added.output
    assert (tmp_path / "data" / "ground-truth" / "toy" / "scan_a.labels").is_file()
    listed = run(cli, "admin", "list-challenges", "--data-dir", data)
    assert "toy\tcustom\t2 scans\topen" in listed.output

    user = run(
        cli,
        "admin",
        "create-user",
        "root",
        "--admin",
        "--data-dir",
        data,
        input=f"{PASSWORD}\n{PASSWORD}\n",
    )
    assert user.exit_code == 0, user.output
    assert "account root created (admin)" in user.output
    run(cli, "admin", "create-user", "bob", "--data-dir", data, input=f"{PASSWORD}\n" * 2)
    promoted = run(cli, "admin", "set-admin", "bob", "--data-dir", data)
    assert promoted.exit_code == 0 and "bob is now an admin" in promoted.output
    demoted = run(cli, "admin", "set-admin", "BOB", "--revoke", "--data-dir", data)
    assert demoted.exit_code == 0 and "bob is no longer an admin" in demoted.output
    unknown = run(cli, "admin", "set-admin", "carol", "--data-dir", data)
    assert unknown.exit_code == 2 and "no account named 'carol'" in unknown.output
    token = run(cli, "admin", "create-token", "root", "--data-dir", data)
    assert token.exit_code == 0 and token.output.strip().startswith("s3d_")
    assert run(cli, "worker", "--once", "--data-dir", data).output.strip() == "queue empty"


def test_admin_errors_are_one_red_line(
    cli: typer.Typer, tmp_path: Path, ground_truth_dir: Path
) -> None:
    data = str(tmp_path / "data")
    run(
        cli,
        "admin",
        "add-challenge",
        "toy",
        "--ground-truth",
        str(ground_truth_dir),
        "--data-dir",
        data,
    )
    again = run(
        cli,
        "admin",
        "add-challenge",
        "toy",
        "--ground-truth",
        str(ground_truth_dir),
        "--data-dir",
        data,
    )
    assert again.exit_code == 2
    assert "already installed" in again.output
    bad = run(
        cli,
        "admin",
        "add-challenge",
        "Bad Name",
        "--ground-truth",
        str(ground_truth_dir),
        "--data-dir",
        data,
    )
    assert bad.exit_code == 2 and "challenge name 'Bad Name'" in bad.output
    nobody = run(cli, "admin", "create-token", "ghost", "--data-dir", data)
    assert nobody.exit_code == 2 and "no account named 'ghost'" in nobody.output


def test_a_broken_ground_truth_folder_is_refused_and_leaves_nothing(
    cli: typer.Typer, tmp_path: Path
) -> None:
    folder = tmp_path / "gt"
    folder.mkdir()
    (folder / "scan.labels").write_text("1\n2\nbanana\n")
    data = tmp_path / "data"
    result = run(
        cli,
        "admin",
        "add-challenge",
        "broken",
        "--ground-truth",
        str(folder),
        "--data-dir",
        str(data),
    )
    assert result.exit_code == 2 and "line 3" in result.output
    assert not (data / "ground-truth" / "broken").exists()
    assert "broken" not in run(cli, "admin", "list-challenges", "--data-dir", str(data)).output


def test_benchmark_challenge_needs_its_scans(
    cli: typer.Typer, tmp_path: Path, ground_truth_dir: Path
) -> None:
    result = run(
        cli,
        "admin",
        "add-challenge",
        "reduced-8",
        "--ground-truth",
        str(ground_truth_dir),
        "--data-dir",
        str(tmp_path / "data"),
    )
    assert result.exit_code == 2
    assert "expected ground truth of every reduced-8 scan" in result.output


def test_an_admin_command_loads_no_web_framework_and_computes_no_dummy_hash(
    cli: typer.Typer, tmp_path: Path
) -> None:
    """``create-token`` reads and writes the database only: neither FastAPI (0.6 s to
    import) nor an argon2 hash (64 MiB, ~0.2 s) before its work."""
    import json
    import subprocess
    import sys
    import textwrap

    data = str(tmp_path / "data")
    created = run(
        cli, "admin", "create-user", "alice", "--data-dir", data, input=f"{PASSWORD}\n" * 2
    )
    assert created.exit_code == 0, created.output
    code = textwrap.dedent(f"""
        import contextlib, io, json, sys
        from semantic3d.cli.server import _main
        sys.argv = ["semantic3d-server", "admin", "create-token", "alice", "--data-dir", {data!r}]
        with contextlib.redirect_stdout(io.StringIO()) as shown:
            try:
                _main()
            except SystemExit as exc:
                assert not exc.code, exc.code
        from semantic3d.server.services import accounts
        print(json.dumps([
            shown.getvalue(), "fastapi" in sys.modules, accounts.dummy_hash.cache_info().currsize
        ]))
    """)
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 0, done.stderr
    token, fastapi_loaded, dummy_hashes = json.loads(done.stdout.strip().splitlines()[-1])
    assert token.startswith("s3d_")
    assert fastapi_loaded is False
    assert dummy_hashes == 0


def test_the_server_makes_the_dummy_hash_before_any_login(tmp_path: Path) -> None:
    from semantic3d.server.app import create_app
    from semantic3d.server.services import accounts
    from semantic3d.server.settings import Settings

    accounts.dummy_hash.cache_clear()
    create_app(Settings(data_dir=tmp_path / "data"))
    assert accounts.dummy_hash.cache_info().currsize == 1
