"""The simulator's error: bad arguments and invalid scene descriptions."""

from __future__ import annotations

from semantic3d.core.errors import Semantic3DError


class SimulationConfigError(Semantic3DError, ValueError):
    """An argument or a scene description is invalid (unknown scene, ``n_points <= 0``, ...)."""
