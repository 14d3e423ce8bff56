"""The default procedural scenes, one module each, and :func:`build_scene`."""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum

from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.scene import Scene


class SceneName(StrEnum):
    """The default scenes."""

    VILLAGE = "village"
    STREET = "street"
    SQUARE = "square"
    RAILWAY = "railway"


def build_scene(name: SceneName | str, *, seed: int = 0) -> Scene:
    """Lay out the default scene ``name``; ``seed`` fixes every random choice of the layout."""
    scene_name = validate_scene_name(name)
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise SimulationConfigError(f"seed: expected a non-negative integer, found {seed!r}")
    return _builders()[scene_name](int(seed))


def validate_scene_name(name: SceneName | str) -> SceneName:
    """``name`` as a :class:`SceneName`, or :class:`SimulationConfigError` naming the choices."""
    try:
        return SceneName(name)
    except ValueError:
        known = ", ".join(s.value for s in SceneName)
        raise SimulationConfigError(f"unknown scene {name!r}: expected one of {known}") from None


def _builders() -> dict[SceneName, Callable[[int], Scene]]:
    from semantic3d.datasets.simulator.scenes.railway import build_railway
    from semantic3d.datasets.simulator.scenes.square import build_square
    from semantic3d.datasets.simulator.scenes.street import build_street
    from semantic3d.datasets.simulator.scenes.village import build_village

    return {
        SceneName.VILLAGE: build_village,
        SceneName.STREET: build_street,
        SceneName.SQUARE: build_square,
        SceneName.RAILWAY: build_railway,
    }
