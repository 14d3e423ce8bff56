"""Shared fixtures: paths to the real samples and small generated clouds."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real labelled samples; tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("real samples in ../shared/data are not available")
    return SHARED_DATA
