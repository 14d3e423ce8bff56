"""The 3D workflow: a model fitted through picked points, previewed, then its inliers kept.

Candidates are the editable working points in the fit's region (default: a sphere around
the picks), sampled uniformly (at most 200 000) in one compiled pass over the octree nodes
that meet the region (their float32 re-centred positions: micrometres at a kilometre); the model (RANSAC and
least squares, :func:`~semantic3d.labelling.geometry.fit_model`) passes within the tolerance
of every pick; its inliers are the working points within the tolerance of it and inside the
region, selected in a second compiled pass over the same nodes (every other working point
leaves the working set without being read); a fit without a region reads the whole scan. A preview counts them and keeps a
uniform sample to draw, changing nothing; a previewed model can be committed as it is.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.labelling import _op_kernels as kernels
from semantic3d.labelling import geometry
from semantic3d.labelling.delta import Delta, empty_bits
from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.fitting import NO_REGION, Region, model_arrays, model_from_dict
from semantic3d.labelling.results import (
    MAX_RADIUS_M,
    MAX_SEEDS,
    MAX_TOLERANCE_M,
    OperationResult,
    _check_distance,
    _finite,
)
from semantic3d.labelling.session import LabelSession, _Running

__all__ = ["PREVIEW_POINTS", "FitPreview", "fit", "fit_preview"]

_CANDIDATES_MAX = 200_000
PREVIEW_POINTS = 30_000
"""Inliers a preview sends back to draw (a uniform sample)."""


@dataclass(frozen=True, slots=True)
class FitPreview:
    """A fitted model and its inliers, before anything changes."""

    model: dict[str, Any]
    region: dict[str, Any] | None
    n_inliers: int
    rms_m: float | None
    sample: NDArray[np.float32]
    """A uniform sample of the inliers (re-centred metres), for the page to draw."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "region": self.region,
            "n_inliers": self.n_inliers,
            "rms_m": _finite(self.rms_m),
            "sample": np.round(self.sample.astype(np.float64), 4).tolist(),
        }


def _fit_inputs(
    session: LabelSession, kind: str, seeds: ArrayLike, tolerance_m: float, radius_m: float | None
) -> tuple[geometry.ModelKind, NDArray[np.float64], float, float]:
    try:
        model_kind = geometry.ModelKind(kind)
    except ValueError:
        known = ", ".join(k.value for k in geometry.ModelKind)
        raise OperationError(f"kind: expected one of {known}, found {kind!r}") from None
    try:
        seed_xyz = np.asarray(seeds, np.float64).reshape(-1, 3)
    except (TypeError, ValueError):
        raise OperationError("seeds: expected a list of [x, y, z] points") from None
    if not 1 <= len(seed_xyz) <= MAX_SEEDS:
        raise OperationError(
            f"seeds: expected 1 to {MAX_SEEDS} picked points, found {len(seed_xyz)}"
        )
    if not np.isfinite(seed_xyz).all():
        raise OperationError("seeds: expected finite coordinates, found NaN or infinity")
    tolerance = _check_distance("tolerance_m", tolerance_m, MAX_TOLERANCE_M)
    centre = seed_xyz.mean(axis=0)
    spread = float(np.linalg.norm(seed_xyz - centre, axis=1).max())
    radius = (
        _check_distance("radius_m", radius_m, MAX_RADIUS_M)
        if radius_m is not None
        else max(1.5 * spread, 1.0)
    )
    return model_kind, seed_xyz, tolerance, radius


READ_POINTS = 1 << 20
"""Points of consecutive nodes a fit in a region reads at once (a larger node in parts)."""


def _region_pieces(
    session: LabelSession, region: Region
) -> Generator[tuple[NDArray[np.float32], NDArray[Any], list[tuple[int, bool]]], None, None]:
    """The points of the octree nodes meeting ``region``'s box, in node order, read in
    pieces of consecutive nodes: ``(re-centred positions, scan indices, ends)``, ``ends``
    the piece's parts ``(end, whether a node ends there)``.

    Coarse nodes first (ids are breadth first): a caller that stops early (the fit's
    candidates) has an even sample of the region, since coarse nodes are uniform
    subsamples of their cubes, not one crowded near the scanner.
    """
    if region.kind == "sphere":
        assert region.centre is not None
        low, high = region.centre - region.radius_m, region.centre + region.radius_m
    else:
        assert region.low is not None and region.high is not None
        low, high = region.low, region.high
    lod = session.lod
    meets = (
        (lod.node_counts > 0)
        & (lod.node_bounds[:, :3] <= high).all(axis=1)
        & (lod.node_bounds[:, 3:] >= low).all(axis=1)
    )
    ids = np.flatnonzero(meets)
    starts, counts = lod.node_starts[ids].tolist(), lod.node_counts[ids].tolist()
    total = int(sum(counts))
    session.progress.set_total(total)
    pieces: list[tuple[int, list[tuple[int, bool]]]] = []  # (start, ends)
    for start, count in zip(starts, counts, strict=True):
        if pieces:
            first, ends = pieces[-1]
            end = first + ends[-1][0]
            if end == start and ends[-1][0] + count <= READ_POINTS:
                ends.append((ends[-1][0] + count, True))
                continue
        for part in range(0, count, READ_POINTS):
            size = min(READ_POINTS, count - part)
            pieces.append((start + part, [(size, part + size == count)]))
    done = 0
    for start, ends in pieces:
        session.progress.update(done)
        count = ends[-1][0]
        yield lod.read_positions(start, count), lod.read_indices(start, count), ends
        done += count
    session.progress.update(total)


def _fit(
    session: LabelSession,
    kind: str,
    seeds: ArrayLike,
    tolerance_m: float,
    radius_m: float | None,
    region: Region | None,
    model: dict[str, Any] | None,
) -> tuple[geometry.Model, geometry.ModelKind, NDArray[np.float64], float, float | None]:
    """The model through the seeds (fitted on candidates in the region, or the one given).

    Returns the model, its kind, the seeds, the tolerance and the rms distance of the
    candidate inliers (``None`` for a given model).
    """
    model_kind, seed_xyz, tolerance, radius = _fit_inputs(
        session, kind, seeds, tolerance_m, radius_m
    )
    if model is not None:
        fitted = model_from_dict(model)
        if fitted.to_dict()["kind"] != model_kind.value:
            raise OperationError(f"model: expected a {model_kind.value}, found {model!r}")
        if not (fitted.distance(seed_xyz) <= tolerance).all():
            raise OperationError("model: expected a model within tolerance of every pick")
        return fitted, model_kind, seed_xyz, tolerance, None
    search = region or Region.sphere(seed_xyz.mean(axis=0), radius)
    code, parameters = search.kernel()
    candidates = np.empty((_CANDIDATES_MAX, 3))
    filled = seen = 0
    editable = session.editable_layers()
    pieces = _region_pieces(session, search)
    for positions, index, ends in pieces:
        begin = 0
        for end, node_ends in ends:
            filled, seen = kernels.region_candidates_at(
                positions[begin:end], index[begin:end], session.labels, session.working,
                editable, code, parameters, candidates, filled, seen,
            )  # fmt: skip
            begin = end
            if node_ends and filled >= _CANDIDATES_MAX:  # enough, from the coarsest nodes
                break
        else:
            continue
        pieces.close()
        break
    try:
        fitted_result = geometry.fit_model(
            model_kind, candidates[:filled], tolerance_m=tolerance, seeds=seed_xyz
        )
    except ValueError as exc:
        raise OperationError(f"fit {model_kind.value}: {exc}") from None
    return fitted_result.model, model_kind, seed_xyz, tolerance, fitted_result.rms_m


def fit_preview(
    session: LabelSession,
    kind: str,
    seeds: ArrayLike,
    *,
    tolerance_m: float,
    radius_m: float | None = None,
    region: Region | None = None,
) -> FitPreview:
    """Fit a model through ``seeds`` and count its inliers in ``region``; change nothing."""
    with session.lock, _Running(session, "fit preview"):
        fitted, _, _, tolerance, _ = _fit(session, kind, seeds, tolerance_m, radius_m, region, None)
        code, parameters = model_arrays(fitted)
        region_code, region_parameters = NO_REGION if region is None else region.kernel()
        sample = np.empty((PREVIEW_POINTS, 3))
        filled = seen = 0
        squares = 0.0
        editable = session.editable_layers()
        if region is None:
            for start, xyz in session.iter_blocks():
                filled, seen, block_squares = kernels.inlier_sample(
                    xyz, start, session.origin, session.labels, session.working, editable,
                    code, parameters, tolerance, region_code, region_parameters, sample,
                    filled, seen,
                )  # fmt: skip
                squares += block_squares
        else:
            for positions, index, _ in _region_pieces(session, region):
                filled, seen, block_squares = kernels.inlier_sample_at(
                    positions, index, session.labels, session.working, editable, code, parameters,
                    tolerance, region_code, region_parameters, sample, filled, seen,
                )  # fmt: skip
                squares += block_squares
        return FitPreview(
            fitted.to_dict(),
            None if region is None else region.to_dict(),
            int(seen),
            math.sqrt(squares / seen) if seen else None,
            sample[:filled].astype(np.float32),
        )


def fit(
    session: LabelSession,
    kind: str,
    seeds: ArrayLike,
    *,
    tolerance_m: float,
    radius_m: float | None = None,
    region: Region | None = None,
    model: dict[str, Any] | None = None,
) -> OperationResult:
    """Fit a model through ``seeds`` (re-centred metres); the working set keeps its inliers.

    Candidates are the working points in ``region`` (default: within ``radius_m`` of
    the seeds' centre, by default 1.5 × the seeds' spread, at least 1 m). The model
    (``model``: a previewed one, committed as it is) passes within ``tolerance_m`` of
    every seed; its inliers are the working points within ``tolerance_m`` of it and
    inside ``region`` (the whole scan when there is none).
    """
    with session.lock, session._run("fit"):
        fitted, model_kind, seed_xyz, tolerance, rms = _fit(
            session, kind, seeds, tolerance_m, radius_m, region, model
        )
        code, parameters = model_arrays(fitted)
        region_code, region_parameters = NO_REGION if region is None else region.kernel()
        flip = empty_bits(session.n_points)
        editable = session.editable_layers()
        if region is None:
            session.map_blocks(
                lambda start, xyz: kernels.fit_flips(
                    xyz, start, session.origin, session.labels, session.working, editable,
                    code, parameters, tolerance, region_code, region_parameters, flip,
                )
            )  # fmt: skip
        else:  # every active point leaves, but the inliers of the nodes meeting the region
            kernels.mark_active(session.labels, session.working, editable, flip)
            for positions, index, _ in _region_pieces(session, region):
                kernels.keep_inliers_at(
                    positions, index, session.labels, session.working, editable, code, parameters,
                    tolerance, region_code, region_parameters, flip,
                )  # fmt: skip
        operation = {
            "name": "fit",
            "kind": model_kind.value,
            "seeds": seed_xyz.tolist(),
            "tolerance_m": tolerance,
            "radius_m": radius_m,
            "region": None if region is None else region.to_dict(),
            "model": fitted.to_dict(),
        }
        delta = Delta.working_only(session.n_points, flip)
        _, n_before = kernels.count_active(session.labels, session.working, editable)
        n_inliers = int(n_before) - delta.n_flipped
        return session._commit(
            operation, delta, model=fitted.to_dict(), n_inliers=n_inliers, rms_m=rms
        )
