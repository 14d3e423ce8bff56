"""The spatial layer's doctests run, and importing the package compiles nothing."""

from __future__ import annotations

import doctest
import importlib
import subprocess
import sys

import pytest


@pytest.mark.parametrize("name", ["voxels", "grid", "store", "job"])
def test_doctests(name: str) -> None:
    module = importlib.import_module(f"semantic3d.spatial.{name}")
    result = doctest.testmod(module)
    assert result.attempted > 0 and result.failed == 0


def test_package_import_is_lazy() -> None:
    code = "import sys, semantic3d.spatial as s; s.TileGrid; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
