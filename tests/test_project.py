"""Project-level checks: the front door, lint, formatting and the layer contract."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    path = BIN / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    if found is None:
        pytest.skip(f"{name} is not installed")
    return found


def test_readme_starts_with_the_two_commands() -> None:
    readme = (ROOT / "README.md").read_text()
    head = readme[: readme.index("```", readme.index("```") + 3)]
    assert "make demo" in head and "make test" in head
    assert "make test" in (ROOT / ".ci" / "run").read_text()


def _make_dry_run(target: str, venv: Path) -> list[str]:
    """The commands ``make TARGET`` would run on a fresh clone (``make -n``: none is run)."""
    make = shutil.which("make")
    if make is None:
        pytest.skip("make is not installed")
    # Not the variables of a `make test` that may be running this suite.
    inherited = ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "PYTEST_ARGS", "DEMO_ARGS")
    env = {key: value for key, value in os.environ.items() if key not in inherited}
    done = subprocess.run(
        [make, "-n", target, f"VENV={venv}"], cwd=ROOT, capture_output=True, text=True, env=env
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_make_demo_installs_only_the_demo_extra_and_says_how_much(tmp_path: Path) -> None:
    # A fresh clone: `make demo` used to install [all] (6.2 GB with CUDA torch); it installs
    # the demo extra (no torch, Dask or image stack), says what and how big, shows progress.
    commands = _make_dry_run("demo", tmp_path / ".venv")
    installs = [line for line in commands if "pip install" in line and "-e" in line.split()]
    assert len(installs) == 1 and installs[0].endswith("-e '.[demo]'"), commands
    assert "--progress-bar on" in installs[0] and "--quiet" not in installs[0]
    said = " ".join(commands[: commands.index(installs[0])])
    assert "installing semantic3d" in said and " MB" in said, said
    assert commands[-1].endswith("/bin/semantic3d demo --serve")
    # `make test` keeps every extra and the test tools.
    tests = _make_dry_run("test", tmp_path / ".venv")
    assert any(line.endswith("-e '.[test]'") for line in tests), tests
    assert "-m pytest -n 2" in tests[-1]


def test_ruff_lint_is_clean() -> None:
    result = subprocess.run(
        [_tool("ruff"), "check", "src", "tests", "benchmarks"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_format_is_clean() -> None:
    result = subprocess.run(
        [_tool("ruff"), "format", "--check", "src", "tests", "benchmarks"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_layers_point_one_way() -> None:
    result = subprocess.run([_tool("lint-imports")], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_io_modules_import_no_cycle() -> None:
    """No import cycle among the io modules: the cache format never imports the format
    dispatch that reads caches (io/conversion holds what needs both)."""
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("semantic3d")
    modules = sorted(graph.find_children("semantic3d.io"))
    imports = {
        module: {m for m in graph.find_modules_directly_imported_by(module) if m in modules}
        for module in modules
    }
    assert "semantic3d.io.formats" not in imports["semantic3d.io.cache"]

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        return any(nxt == goal or reaches(nxt, goal, seen | {nxt}) for nxt in imports[start] - seen)

    cycles = [module for module in modules if reaches(module, module, set())]
    assert cycles == []
