"""The simulator's error: bad arguments and invalid scene descriptions."""

from __future__ import annotations

from semantic3d.core.errors import ConfigError


class SimulationConfigError(ConfigError):
    """An argument or a scene description is invalid (unknown scene, ``n_points <= 0``, ...).

    A :class:`~semantic3d.core.errors.ConfigError` (and so a ``ValueError``): callers that
    handle bad configuration handle the simulator's too.
    """
