"""Start-up cost and the core install: what building the app imports, and every command on a
Python where the extras are missing (imports blocked in a subprocess)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.io.ascii import write_ascii_points
from tests.factories import random_cloud

REPO = Path(__file__).resolve().parents[2]

#: Never imported to build the app, run --version or show --help.
HEAVY = (
    "numpy",
    "numba",
    "sklearn",
    "scipy",
    "pandas",
    "fastapi",
    "sqlalchemy",
    "uvicorn",
    "httpx",
    "matplotlib",
    "laspy",
    "plyfile",
    "py7zr",
    "pyproj",
    "markdown_it",
    "pygments",
)

#: The packages the extras install (``pyproject.toml``); blocked to act as a core install.
EXTRAS = (
    "sklearn",
    "scipy",
    "joblib",
    "pgeof",
    "laspy",
    "lazrs",
    "pyproj",
    "plyfile",
    "py7zr",
    "matplotlib",
    "fastapi",
    "starlette",
    "uvicorn",
    "sqlalchemy",
    "alembic",
    "jinja2",
    "multipart",
    "argon2",
    "itsdangerous",
    "pydantic_settings",
    "httpx",
    "psycopg",
    "pandas",
    "pyarrow",
    "polars",
)

_BLOCKER = """
import importlib.abc, sys

class _Blocked(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, _Blocked())
"""


def _python(code: str, *args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "COLUMNS": "200"},
    )


def _loaded_after(statement: str) -> list[str]:
    code = textwrap.dedent(f"""
        import io, json, sys, contextlib
        with contextlib.redirect_stdout(io.StringIO()):
            try:
                {statement}
            except SystemExit:
                pass
        print(json.dumps(sorted({{m.partition(".")[0] for m in sys.modules}})))
    """)
    done = _python(code)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.mark.parametrize(
    "statement",
    [
        "import semantic3d.cli.app",
        "sys.argv = ['semantic3d', '--version']; from semantic3d.cli.app import main; main()",
        "sys.argv = ['semantic3d', '--help']; from semantic3d.cli.app import main; main()",
    ],
    ids=["import", "--version", "--help"],
)
def test_building_the_app_imports_nothing_heavy(statement: str) -> None:
    loaded = _loaded_after(statement)
    assert [name for name in HEAVY if name in loaded] == []


def test_package_imports_are_lazy() -> None:
    statement = (
        "import semantic3d, semantic3d.core, semantic3d.io, semantic3d.metrics, "
        "semantic3d.datasets, semantic3d.datasets.simulator, semantic3d.features, "
        "semantic3d.evaluation, semantic3d.viz, semantic3d.baselines.covariance"
    )
    loaded = _loaded_after(statement)
    assert [
        name for name in ("numpy", "numba", "sklearn", "scipy", "matplotlib") if name in loaded
    ] == []


def test_lazy_exports_resolve_on_first_use() -> None:
    import semantic3d.io
    from semantic3d.io.formats import iter_points

    assert semantic3d.io.iter_points is iter_points
    assert "iter_points" in dir(semantic3d.io)
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        _ = semantic3d.io.nope  # type: ignore[attr-defined]


def test_constants_repeated_for_start_up_match_the_library() -> None:
    from semantic3d.cli import convert, download, evaluate, simulate
    from semantic3d.datasets.registry import Split
    from semantic3d.datasets.simulator import MAX_STATIONS, SceneName
    from semantic3d.evaluation import agreement
    from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE

    assert convert.DEFAULT_CHUNK_SIZE == simulate.DEFAULT_CHUNK_SIZE == DEFAULT_CHUNK_SIZE
    assert tuple(s.value for s in SceneName) == simulate.SCENE_NAMES
    assert simulate.MAX_STATIONS == MAX_STATIONS
    assert evaluate.DEFAULT_MAX_DISTANCE_M == agreement.DEFAULT_MAX_DISTANCE_M
    assert evaluate.DEFAULT_TILE_SIZE_M == agreement.DEFAULT_TILE_SIZE_M
    assert [c.value for c in download.SplitChoice][:-1] == [s.value for s in Split]


def test_help_shows_no_type_after_flags() -> None:
    runner = CliRunner()
    for args in (["--help"], ["convert", "--help"], ["serve", "--help"]):
        result = runner.invoke(app, args, terminal_width=200)
        assert result.exit_code == 0, result.output
        assert "<bool>" not in result.output
    assert "--overwrite " in runner.invoke(app, ["convert", "--help"]).output


@pytest.fixture(scope="module")
def core_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A scan, its ground truth and a valid prediction folder."""
    folder = tmp_path_factory.mktemp("core")
    cloud = random_cloud(300, seed=4)
    write_ascii_points(folder / "scan.txt", [cloud], labels_path=folder / "scan.labels")
    (folder / "gt").mkdir()
    (folder / "gt" / "scan.labels").write_bytes((folder / "scan.labels").read_bytes())
    (folder / "pred").mkdir()
    (folder / "pred" / "scan.labels").write_text("".join(f"{1 + i % 8}\n" for i in range(300)))
    return folder


def _core(folder: Path, *args: str) -> subprocess.CompletedProcess[str]:
    code = _BLOCKER.format(blocked=set(EXTRAS)) + (
        "from semantic3d.cli.app import main\nsys.argv = ['semantic3d', *sys.argv[1:]]\nmain()\n"
    )
    return _python(code, *args, cwd=folder)


@pytest.mark.parametrize(
    "args",
    [
        ["--version"],
        ["--help"],
        ["info", "scan.txt"],
        ["convert", "scan.txt", "out/scan.cache"],
        ["validate", "pred", "--gt", "gt"],
        ["evaluate", "--gt", "gt", "--pred", "pred", "--json", "r.json", "--overwrite"],
        *([name, "--help"] for name in ("convert", "evaluate", "serve", "submit", "simulate")),
        ["baseline", "covariance", "predict", "--help"],
        ["admin", "create-user", "--help"],
    ],
    ids=" ".join,
)
def test_the_core_install_runs(core_folder: Path, args: list[str]) -> None:
    done = _core(core_folder, *args)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Traceback" not in done.stderr


def test_the_core_install_converts_ascii_to_cache_and_back(
    core_folder: Path, tmp_path: Path
) -> None:
    cache = tmp_path / "scan.cache"
    assert _core(core_folder, "convert", "scan.txt", str(cache)).returncode == 0
    done = _core(core_folder, "convert", str(cache), str(tmp_path / "back.txt"))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "back.txt").read_bytes() == (core_folder / "scan.txt").read_bytes()
    assert (tmp_path / "back.labels").read_bytes() == (core_folder / "scan.labels").read_bytes()


@pytest.mark.parametrize(
    ("args", "extra"),
    [
        (["convert", "scan.txt", "x.las"], "las"),
        (["convert", "scan.txt", "x.laz"], "las"),
        (["convert", "scan.txt", "x.ply"], "ply"),
        (["evaluate", "--gt", "gt", "--pred", "pred", "--report", "r.html"], "viz"),
        (["stats", "gt", "--plot", "p.png"], "viz"),
        (["agreement", "scan.txt", "scan.labels", "scan.txt", "scan.labels"], "sim"),
        (["baseline", "covariance", "train", "--data", ".", "--out", "m.s3d"], "ml"),
        (["baseline", "covariance", "predict", "scan.txt", "--model", "m.s3d"], "ml"),
        (["download", "--split", "reduced-8", "--to", "data"], "download"),
        (["serve"], "server"),
        (["worker", "--once"], "server"),
        (
            [
                "submit",
                "scan.txt",
                "--server",
                "http://h",
                "--challenge",
                "c",
                "--token",
                "t",
                "--method",
                "m",
            ],
            "server",
        ),
    ],
    ids=lambda value: " ".join(value) if isinstance(value, list) else value,
)
def test_a_command_needing_an_extra_says_which_in_one_line(
    core_folder: Path, args: list[str], extra: str
) -> None:
    done = _core(core_folder, *args)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines == [lines[0]] and lines[0].startswith("error: ")
    assert f"pip install 'semantic3d[{extra}]'" in lines[0]


@pytest.mark.slow
def test_a_fresh_core_install_in_its_own_venv(tmp_path: Path, core_folder: Path) -> None:
    """``pip install`` of the package with no extras into a new virtual environment."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet"]
    import tomllib

    core = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    try:
        subprocess.run([*pip, *core], check=True, timeout=1800)
    except subprocess.CalledProcessError:
        pytest.skip("the package index is not reachable")
    subprocess.run([*pip, "--no-deps", "-e", str(REPO)], check=True, timeout=600)
    semantic3d = str(venv / "bin" / "semantic3d")

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [semantic3d, *args], cwd=core_folder, capture_output=True, text=True, timeout=600
        )

    for args in (
        ["--version"],
        ["info", "scan.txt"],
        ["convert", "scan.txt", str(tmp_path / "s.cache")],
        ["convert", str(tmp_path / "s.cache"), str(tmp_path / "back.txt")],
        ["validate", "pred", "--gt", "gt"],
        ["evaluate", "--gt", "gt", "--pred", "pred"],
    ):
        done = run(*args)
        assert done.returncode == 0, (args, done.stderr)
    done = run("convert", "scan.txt", str(tmp_path / "x.las"))
    assert done.returncode == 2 and "pip install 'semantic3d[las]'" in done.stderr
    done = run("serve")
    assert done.returncode == 2 and "pip install 'semantic3d[server]'" in done.stderr


def test_small_inputs_load_no_compiled_kernels(core_folder: Path) -> None:
    """Importing numba and loading its kernels (which pulls in scipy) costs over a
    CPU-second; small files are parsed and counted with numpy instead."""
    commands = [
        ["info", "scan.txt"],
        ["validate", "pred", "--gt", "gt"],
        ["evaluate", "--gt", "gt", "--pred", "pred"],
    ]
    code = textwrap.dedent(f"""
        import contextlib, io, json, sys
        from semantic3d.cli.app import main
        results = []
        for args in {commands!r}:
            sys.argv = ["semantic3d", *args]
            status = 0
            with contextlib.redirect_stdout(io.StringIO()) as shown:
                try:
                    main()
                except SystemExit as exc:
                    status = exc.code or 0
            results.append([status, shown.getvalue()])
        loaded = sorted({{m.partition(".")[0] for m in sys.modules}})
        print(json.dumps([results, loaded]))
    """)
    done = _python(code, cwd=core_folder)
    assert done.returncode == 0, done.stderr
    results, loaded = json.loads(done.stdout)
    assert [status for status, _ in results] == [0, 0, 0], results
    assert "300" in results[0][1] and "valid" in results[1][1] and "mIoU" in results[2][1]
    assert [name for name in ("numba", "llvmlite", "scipy", "sklearn") if name in loaded] == []
