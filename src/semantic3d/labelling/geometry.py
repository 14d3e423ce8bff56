"""Server-side geometry of the two labelling workflows: polygon splits and model fits.

2D workflow: a point is *inside* a polygon drawn on the screen when its projection by the
camera's view-projection matrix (4×4, row-major, ``clip = M @ [x, y, z, 1]`` with ``x y z``
re-centred on the scan origin) lands inside the polygon in normalised device coordinates
and is in front of the camera (``w > 0``). The polygon extrudes through every depth, as
the paper's fixed-view cut does.

3D workflow: RANSAC over a sample of candidate points proposes models from minimal sets
(3 points for a plane, 2 for a line, 4 for a sphere; a cylinder's axis comes from the
principal direction of the candidates and its circle from 3 projected points), keeps the
one with most points within ``tolerance_m``, then refits it by least squares on its inliers
(plane and line: principal axes; sphere: the algebraic fit; cylinder: a geometric
Levenberg-Marquardt fit of axis and radius). Distances are Euclidean, in
metres, to the surface (to the axis for a line).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError

__all__ = [
    "CylinderModel",
    "FitResult",
    "LineModel",
    "Model",
    "ModelKind",
    "PlaneModel",
    "SphereModel",
    "fit_model",
    "points_in_polygon",
    "project_to_ndc",
    "select_in_polygon",
]

_RANSAC_ITERATIONS = 256
_SCORE_SAMPLE = 50_000


class ModelKind(StrEnum):
    """The models the 3D workflow fits."""

    PLANE = "plane"
    LINE = "line"
    CYLINDER = "cylinder"
    SPHERE = "sphere"


class Model(Protocol):
    """A fitted surface: distances of points to it, and a JSON description."""

    def distance(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]: ...

    def to_dict(self) -> dict[str, Any]: ...


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / max(float(np.linalg.norm(v)), 1e-300)


@dataclass(frozen=True, slots=True)
class PlaneModel:
    """The plane through ``point`` with unit ``normal``."""

    point: NDArray[np.float64]
    normal: NDArray[np.float64]

    def distance(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.abs((xyz - self.point) @ self.normal)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "plane", "point": self.point.tolist(), "normal": self.normal.tolist()}


@dataclass(frozen=True, slots=True)
class LineModel:
    """The line through ``point`` along unit ``direction``."""

    point: NDArray[np.float64]
    direction: NDArray[np.float64]

    def distance(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        d = xyz - self.point
        along = d @ self.direction
        return np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - along**2, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "line", "point": self.point.tolist(), "direction": self.direction.tolist()}


@dataclass(frozen=True, slots=True)
class CylinderModel:
    """The infinite cylinder of ``radius_m`` around the line (``point``, unit ``axis``)."""

    point: NDArray[np.float64]
    axis: NDArray[np.float64]
    radius_m: float

    def distance(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.abs(LineModel(self.point, self.axis).distance(xyz) - self.radius_m)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "cylinder",
            "point": self.point.tolist(),
            "axis": self.axis.tolist(),
            "radius_m": self.radius_m,
        }


@dataclass(frozen=True, slots=True)
class SphereModel:
    """The sphere of ``radius_m`` around ``centre``."""

    centre: NDArray[np.float64]
    radius_m: float

    def distance(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.abs(np.linalg.norm(xyz - self.centre, axis=1) - self.radius_m)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "sphere", "centre": self.centre.tolist(), "radius_m": self.radius_m}


@dataclass(frozen=True, slots=True)
class FitResult:
    """A fitted model and which of the fitted points are its inliers."""

    model: Model
    inliers: NDArray[np.bool_]
    rms_m: float

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


# --- projection and polygons ---------------------------------------------------------------


def _as_matrix(view_projection: ArrayLike) -> NDArray[np.float64]:
    matrix = np.asarray(view_projection, np.float64)
    if matrix.shape == (16,):
        matrix = matrix.reshape(4, 4)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ShapeError(
            f"view_projection: expected a finite 4×4 matrix (or 16 numbers, row-major), "
            f"found shape {matrix.shape}"
        )
    return matrix


def _as_polygon(polygon: ArrayLike) -> NDArray[np.float64]:
    vertices = np.asarray(polygon, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 2 or vertices.shape[0] < 3:
        raise ShapeError(
            f"polygon: expected at least 3 (x, y) vertices, found shape {vertices.shape}"
        )
    if not np.isfinite(vertices).all():
        raise ShapeError("polygon: expected finite vertex coordinates, found NaN or infinity")
    return vertices


def project_to_ndc(
    xyz: NDArray[np.float64], view_projection: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Normalised device coordinates ``(n, 2)`` of ``xyz`` and whether each is in front."""
    matrix = _as_matrix(view_projection)
    clip = xyz @ matrix[:, :3].T + matrix[:, 3]
    w = clip[:, 3]
    in_front = w > 1e-12
    safe = np.where(in_front, w, 1.0)
    return clip[:, :2] / safe[:, None], in_front


def points_in_polygon(xy: NDArray[np.float64], polygon: ArrayLike) -> NDArray[np.bool_]:
    """Even-odd rule: which 2D points are inside the closed ``polygon``.

    >>> square = [(0, 0), (1, 0), (1, 1), (0, 1)]
    >>> points_in_polygon(np.array([[0.5, 0.5], [1.5, 0.5]]), square).tolist()
    [True, False]
    """
    vertices = _as_polygon(polygon)
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(xy.shape[0], bool)
    # One vectorised pass per edge: polygons have tens of vertices, scans millions of points.
    x0, y0 = vertices[-1]
    for x1, y1 in vertices:
        crosses = (y0 > y) != (y1 > y)
        if crosses.any():
            t = (y[crosses] - y0) / (y1 - y0)
            hit = x[crosses] < x0 + t * (x1 - x0)
            idx = np.flatnonzero(crosses)[hit]
            inside[idx] = ~inside[idx]
        x0, y0 = x1, y1
    return inside


def select_in_polygon(
    xyz: NDArray[np.float64], view_projection: ArrayLike, polygon: ArrayLike
) -> NDArray[np.bool_]:
    """Which points of ``xyz`` (re-centred) fall inside ``polygon`` (NDC) seen by the camera.

    Same answer as ``project_to_ndc`` then ``points_in_polygon``, in one compiled pass
    without temporaries (the split runs over every working point of the scan).
    """
    matrix = _as_matrix(view_projection)
    vertices = _as_polygon(polygon)
    inside = np.empty(xyz.shape[0], np.bool_)
    _select_kernel()(np.ascontiguousarray(xyz, np.float64), matrix, vertices, inside)
    return inside


_KERNEL: Any = None


def _select_kernel() -> Any:
    # Hand-written hot path: numpy's (n, 3) @ (3, 4) product plus the per-edge passes cost
    # 0.6 s per 10 M points on a laptop core; this fused loop allocates nothing.
    global _KERNEL
    if _KERNEL is None:
        import numba

        @numba.njit(cache=True, nogil=True)
        def kernel(xyz, matrix, vertices, inside):  # type: ignore[no-untyped-def]
            m = vertices.shape[0]
            for i in range(xyz.shape[0]):
                x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
                w = matrix[3, 0] * x + matrix[3, 1] * y + matrix[3, 2] * z + matrix[3, 3]
                if w <= 1e-12:
                    inside[i] = False
                    continue
                u = (matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z + matrix[0, 3]) / w
                v = (matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z + matrix[1, 3]) / w
                result = False
                x0, y0 = vertices[m - 1, 0], vertices[m - 1, 1]
                for k in range(m):
                    x1, y1 = vertices[k, 0], vertices[k, 1]
                    if ((y0 > v) != (y1 > v)) and u < x0 + (v - y0) / (y1 - y0) * (x1 - x0):
                        result = not result
                    x0, y0 = x1, y1
                inside[i] = result

        _KERNEL = kernel
    return _KERNEL


# --- models --------------------------------------------------------------------------------


def _plane_from(points: NDArray[np.float64]) -> PlaneModel | None:
    normal = np.cross(points[1] - points[0], points[2] - points[0])
    norm = float(np.linalg.norm(normal))
    if norm < 1e-12:
        return None
    return PlaneModel(points[0].copy(), normal / norm)


def _line_from(points: NDArray[np.float64]) -> LineModel | None:
    direction = points[1] - points[0]
    if float(np.linalg.norm(direction)) < 1e-12:
        return None
    return LineModel(points[0].copy(), _unit(direction))


def _sphere_from(points: NDArray[np.float64]) -> SphereModel | None:
    a = np.column_stack([2 * points, np.ones(len(points))])
    b = np.einsum("ij,ij->i", points, points)
    try:
        solution, *_ = np.linalg.lstsq(a, b, rcond=None)
    except np.linalg.LinAlgError:
        return None
    if np.linalg.matrix_rank(a) < 4:
        return None
    centre = solution[:3]
    r2 = solution[3] + centre @ centre
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return SphereModel(centre, float(np.sqrt(r2)))


def _circle_from(uv: NDArray[np.float64]) -> tuple[NDArray[np.float64], float] | None:
    a = np.column_stack([2 * uv, np.ones(len(uv))])
    b = np.einsum("ij,ij->i", uv, uv)
    if np.linalg.matrix_rank(a) < 3:
        return None
    solution, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = solution[:2]
    r2 = solution[2] + centre @ centre
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return centre, float(np.sqrt(r2))


def _basis(axis: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = _unit(np.cross(axis, helper))
    return u, np.cross(axis, u)


def _cylinder_from(
    points: NDArray[np.float64],
    axis: NDArray[np.float64],
    basis: tuple[NDArray[np.float64], NDArray[np.float64]],
) -> CylinderModel | None:
    u, v = basis
    circle = _circle_from(np.column_stack([points @ u, points @ v]))
    if circle is None:
        return None
    (cu, cv), radius = circle
    return CylinderModel(cu * u + cv * v, axis, radius)


def _principal_axes(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[Any]]:
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    return centroid, vt


def _refine(kind: ModelKind, model: Model, points: NDArray[np.float64]) -> Model:
    """Least-squares refit on ``points`` (the inliers of ``model``)."""
    minimum = {"plane": 3, "line": 2, "sphere": 4, "cylinder": 5}[kind.value]
    if len(points) < minimum:
        return model
    if kind is ModelKind.PLANE:
        centroid, vt = _principal_axes(points)
        return PlaneModel(centroid, vt[2])
    if kind is ModelKind.LINE:
        centroid, vt = _principal_axes(points)
        return LineModel(centroid, vt[0])
    if kind is ModelKind.SPHERE:
        return _sphere_from(points) or model
    assert isinstance(model, CylinderModel)
    return _refine_cylinder(model, points)


def _refine_cylinder(model: CylinderModel, points: NDArray[np.float64]) -> CylinderModel:
    """Geometric least squares (Levenberg-Marquardt over 5 parameters, numeric Jacobian).

    Hand-written: scipy's ``least_squares`` would do, but importing scipy costs seconds
    at the first fit, longer than the fit itself.
    """
    u, v = _basis(model.axis)
    base = model.point - (model.point @ model.axis) * model.axis
    if len(points) > 20_000:
        points = points[np.random.default_rng(0).choice(len(points), 20_000, replace=False)]

    def unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        axis = _unit(model.axis + p[0] * u + p[1] * v)
        return base + p[2] * u + p[3] * v, axis

    def residuals(p: NDArray[np.float64]) -> NDArray[np.float64]:
        point, axis = unpack(p)
        return LineModel(point, axis).distance(points) - p[4]

    p = np.array([0.0, 0.0, 0.0, 0.0, model.radius_m])
    r = residuals(p)
    damping = 1e-3
    for _ in range(30):
        jacobian = np.empty((len(points), 5))
        for k in range(5):
            step = np.zeros(5)
            step[k] = 1e-7 * max(1.0, abs(p[k]))
            jacobian[:, k] = (residuals(p + step) - r) / step[k]
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ r
        update = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), -gradient)
        trial = p + update
        trial_r = residuals(trial)
        if trial_r @ trial_r < r @ r:
            p, r, damping = trial, trial_r, damping / 10
            if np.abs(update).max() < 1e-10:
                break
        else:
            damping *= 10
            if damping > 1e8:
                break
    point, axis = unpack(p)
    return CylinderModel(point, axis, float(abs(p[4])))


def fit_model(
    kind: ModelKind | str,
    points: ArrayLike,
    *,
    tolerance_m: float,
    seeds: ArrayLike | None = None,
    iterations: int = _RANSAC_ITERATIONS,
    seed: int = 0,
) -> FitResult:
    """Fit a ``kind`` model to ``points`` ``(n, 3)``: RANSAC, then least squares on inliers.

    ``seeds`` (points the user picked) constrain the search: the model returned passes
    within ``tolerance_m`` of **every** seed. The seeds' own least-squares model (when
    there are enough of them) is the first hypothesis, a hypothesis counts only if every
    seed lies within ``tolerance_m`` of it, and a least-squares refinement is kept only
    while it still does. Raises :class:`ShapeError` for too few points, a non-positive
    tolerance, or when no model passes through all the seeds.
    """
    kind = ModelKind(kind)
    xyz = np.asarray(points, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ShapeError(f"points: expected an (n, 3) array, found shape {xyz.shape}")
    if not tolerance_m > 0:
        raise ShapeError(f"tolerance_m: expected a positive distance, found {tolerance_m}")
    minimum = {"plane": 3, "line": 2, "sphere": 4, "cylinder": 5}[kind.value]
    if len(xyz) < minimum:
        raise ShapeError(
            f"points: a {kind.value} needs at least {minimum} points, found {len(xyz)}"
        )
    centre = xyz.mean(axis=0)
    local = xyz - centre  # conditioning: fits in metres around the data
    seed_xyz = None if seeds is None else np.asarray(seeds, np.float64).reshape(-1, 3) - centre
    rng = np.random.default_rng(seed)
    sample = local if len(local) <= _SCORE_SAMPLE else local[rng.choice(len(local), _SCORE_SAMPLE)]
    axis = _principal_axes(sample)[1][0] if kind is ModelKind.CYLINDER else None
    basis = _basis(axis) if axis is not None else None
    size = 3 if kind is ModelKind.CYLINDER else minimum

    def propose(subset: NDArray[np.float64]) -> Model | None:
        if kind is ModelKind.PLANE:
            return _plane_from(subset)
        if kind is ModelKind.LINE:
            return _line_from(subset)
        if kind is ModelKind.SPHERE:
            return _sphere_from(subset)
        assert axis is not None and basis is not None
        return _cylinder_from(subset, axis, basis)

    def acceptable(model: Model) -> bool:
        if seed_xyz is None or len(seed_xyz) == 0:
            return True
        return bool((model.distance(seed_xyz) <= tolerance_m).all())

    best: Model | None = None
    best_score = -1
    if seed_xyz is not None and len(seed_xyz) >= size:
        first = [propose(seed_xyz[:size] if kind is not ModelKind.SPHERE else seed_xyz)]
        if len(seed_xyz) > size:
            first.append(_refine(kind, first[0], seed_xyz) if first[0] is not None else None)
        for candidate in first:
            if candidate is None or not acceptable(candidate):
                continue
            score = int((candidate.distance(sample) <= tolerance_m).sum())
            if score > best_score:
                best, best_score = candidate, score
    for _ in range(iterations):
        candidate = propose(sample[rng.choice(len(sample), size, replace=False)])
        if candidate is None or not acceptable(candidate):
            continue
        score = int((candidate.distance(sample) <= tolerance_m).sum())
        if score > best_score:
            best, best_score = candidate, score
    if best is None:
        n_seeds = 0 if seed_xyz is None else len(seed_xyz)
        raise ShapeError(
            f"points: found no {kind.value} within {tolerance_m:g} m of all {n_seeds} picked "
            "points (raise the tolerance or pick again)"
            if n_seeds
            else f"points: found no {kind.value} through the given points"
        )
    model = best
    for _ in range(3):
        inliers = model.distance(local) <= tolerance_m
        if inliers.sum() < minimum:
            break
        refined = _refine(kind, model, local[inliers])
        if not acceptable(refined):
            break
        model = refined
    distances = model.distance(local)
    inliers = distances <= tolerance_m
    rms = float(np.sqrt(np.mean(distances[inliers] ** 2))) if inliers.any() else float("nan")
    return FitResult(_shift(model, centre), inliers, rms)


def _shift(model: Model, offset: NDArray[np.float64]) -> Model:
    """``model`` moved by ``offset`` (back from the fit's local frame)."""
    if isinstance(model, PlaneModel):
        return PlaneModel(model.point + offset, model.normal)
    if isinstance(model, LineModel):
        return LineModel(model.point + offset, model.direction)
    if isinstance(model, CylinderModel):
        return CylinderModel(model.point + offset, model.axis, model.radius_m)
    assert isinstance(model, SphereModel)
    return SphereModel(model.centre + offset, model.radius_m)
