"""The 3D workflow's parameters: the region that bounds a fit, and models as kernel arrays.

A fit's inliers are the working points within ``tolerance_m`` of the model **and** inside
its region: a sphere (centre, radius) or an axis-aligned box, in metres re-centred on the
scan origin. Without a region the model reaches the whole scan (an infinite plane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.geometry import (
    CylinderModel,
    LineModel,
    Model,
    PlaneModel,
    SphereModel,
)

__all__ = ["Region", "model_arrays", "model_from_dict"]

MAX_EXTENT_M = 100_000.0


def _point(value: Any, name: str) -> NDArray[np.float64]:
    try:
        point = np.asarray(value, np.float64).reshape(3)
    except (TypeError, ValueError):
        raise OperationError(f"{name}: expected [x, y, z], found {value!r}") from None
    if not np.isfinite(point).all() or np.abs(point).max() > MAX_EXTENT_M:
        raise OperationError(f"{name}: expected finite coordinates in metres, found {value!r}")
    return point


def _positive(value: Any, name: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or not (math.isfinite(number) and 0 < number <= MAX_EXTENT_M):
        raise OperationError(
            f"{name}: expected a finite distance in metres, 0 < {name} <= {MAX_EXTENT_M:g}, "
            f"found {value!r}"
        )
    return number


@dataclass(frozen=True, slots=True)
class Region:
    """A sphere (``centre``, ``radius_m``) or a box (``low``, ``high``), re-centred metres."""

    kind: str
    centre: NDArray[np.float64] | None = None
    radius_m: float = 0.0
    low: NDArray[np.float64] | None = None
    high: NDArray[np.float64] | None = None

    @classmethod
    def sphere(cls, centre: Any, radius_m: float) -> Region:
        return cls(
            "sphere",
            centre=_point(centre, "region.centre"),
            radius_m=_positive(radius_m, "region.radius_m"),
        )

    @classmethod
    def box(cls, low: Any, high: Any) -> Region:
        a, b = _point(low, "region.min"), _point(high, "region.max")
        if not (a < b).all():
            raise OperationError(
                f"region: expected min < max on every axis, found {a.tolist()} and {b.tolist()}"
            )
        return cls("box", low=a, high=b)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Region:
        kind = data.get("kind")
        if kind == "sphere":
            return cls.sphere(data.get("centre"), data.get("radius_m"))  # type: ignore[arg-type]
        if kind == "box":
            return cls.box(data.get("min"), data.get("max"))
        raise OperationError(f"region.kind: expected 'sphere' or 'box', found {kind!r}")

    def to_dict(self) -> dict[str, Any]:
        if self.kind == "sphere":
            assert self.centre is not None
            return {"kind": "sphere", "centre": self.centre.tolist(), "radius_m": self.radius_m}
        assert self.low is not None and self.high is not None
        return {"kind": "box", "min": self.low.tolist(), "max": self.high.tolist()}

    def kernel(self) -> tuple[int, NDArray[np.float64]]:
        """``(kind code, parameters)`` for the compiled passes (1 sphere, 2 box)."""
        if self.kind == "sphere":
            assert self.centre is not None
            return 1, np.array([*self.centre, self.radius_m, 0.0, 0.0])
        assert self.low is not None and self.high is not None
        return 2, np.array([*self.low, *self.high])


NO_REGION = (0, np.zeros(6))


def model_arrays(model: Model) -> tuple[int, NDArray[np.float64]]:
    """``(kind code, [px, py, pz, vx, vy, vz, radius])`` of a model for the compiled passes."""
    if isinstance(model, PlaneModel):
        return 0, np.array([*model.point, *model.normal, 0.0])
    if isinstance(model, LineModel):
        return 1, np.array([*model.point, *model.direction, 0.0])
    if isinstance(model, CylinderModel):
        return 2, np.array([*model.point, *model.axis, model.radius_m])
    assert isinstance(model, SphereModel)
    return 3, np.array([*model.centre, 0.0, 0.0, 0.0, model.radius_m])


def _unit(value: Any, name: str) -> NDArray[np.float64]:
    vector = _point(value, name)
    norm = float(np.linalg.norm(vector))
    if norm < 1e-9:
        raise OperationError(f"{name}: expected a non-zero direction, found {value!r}")
    return vector / norm


def model_from_dict(data: dict[str, Any]) -> Model:
    """A model from its ``to_dict`` form (a previewed fit sent back to be committed)."""
    kind = data.get("kind")
    if kind == "plane":
        return PlaneModel(
            _point(data.get("point"), "model.point"), _unit(data.get("normal"), "model.normal")
        )
    if kind == "line":
        return LineModel(
            _point(data.get("point"), "model.point"),
            _unit(data.get("direction"), "model.direction"),
        )
    if kind == "cylinder":
        return CylinderModel(
            _point(data.get("point"), "model.point"),
            _unit(data.get("axis"), "model.axis"),
            _positive(data.get("radius_m"), "model.radius_m"),
        )
    if kind == "sphere":
        return SphereModel(
            _point(data.get("centre"), "model.centre"),
            _positive(data.get("radius_m"), "model.radius_m"),
        )
    raise OperationError(f"model.kind: expected plane, line, cylinder or sphere, found {kind!r}")
