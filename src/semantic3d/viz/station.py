"""Where a scan was taken from: a ``x,y,z`` option, the simulator's pose sidecar, or an estimate.

A cube map is rendered from the scanner's station. Three sources, in the order
:func:`resolve_station` tries them:

1. an explicit position (``--station x,y,z``, :func:`parse_station`);
2. the simulator's JSON sidecar (``<scene>.json`` beside ``<scene>_station<k>.txt``,
   format ``semantic3d-simulation``), whose ``position_m`` is the optical centre;
3. :func:`estimate_station`: a static terrestrial scan is densest around its scanner (point
   density falls with range², and the ground near the tripod is hit at the steepest
   angles), so the station is put over the densest 1 m cell of the XY occupancy (counts
   summed over 3 × 3 cells, each cell counting its densest 0.5 m height slab so that
   facades, which stack many points over few cells, do not win), refined to the count-weighted centre of the cells within
   ``search_radius_m``, at ``height_m`` above the lowest points there. The tripod's blind
   cone leaves a small hole right below the scanner; the ring of dense ground around it
   keeps the weighted centre on it. This suits static scans only: mobile, airborne or
   photogrammetric clouds have no station (docs/baseline_image.md has the measurements).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semantic3d.core.pointcloud import PointCloud
from semantic3d.viz.cubemap import CubeMapError

__all__ = [
    "SIDECAR_FORMAT",
    "StationSource",
    "estimate_station",
    "parse_station",
    "read_sidecar_station",
    "resolve_station",
]

SIDECAR_FORMAT = "semantic3d-simulation"
"""``format`` of the simulator's sidecar (``datasets.simulator.simulation``)."""

Station = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class StationSource:
    """A station and where it came from (``option``, ``sidecar:<file>`` or ``estimated``)."""

    position: Station
    source: str


def parse_station(text: str) -> Station:
    """``"x,y,z"`` (metres) as a tuple.

    >>> parse_station("1.5, -2, 0.25")
    (1.5, -2.0, 0.25)

    Raises:
        CubeMapError: not three finite numbers separated by commas.
    """
    parts = [part.strip() for part in str(text).split(",")]
    try:
        values = tuple(float(part) for part in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise CubeMapError(f"station: expected x,y,z (three numbers in metres), found {text!r}")
    return (values[0], values[1], values[2])


def read_sidecar_station(points_path: str | Path) -> Station | None:
    """The station of a simulated scan from the sidecar beside it, or None without one.

    Every ``*.json`` of the scan's folder in the simulator's format is read; the station
    whose ``points`` file name is the scan's gives the position.

    Raises:
        CubeMapError: a sidecar names the scan but holds no usable position.
    """
    path = Path(points_path)
    folder = path.parent
    if not folder.is_dir():
        return None
    for candidate in sorted(folder.glob("*.json")):
        try:
            data = json.loads(candidate.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(data, dict) or data.get("format") != SIDECAR_FORMAT:
            continue
        for record in data.get("stations", []):
            if isinstance(record, dict) and record.get("points") == path.name:
                position = record.get("position_m")
                try:
                    return parse_station(",".join(str(float(v)) for v in list(position or ())))
                except (TypeError, ValueError):
                    raise CubeMapError(
                        f"{candidate}: station of {path.name}: expected position_m [x, y, z], "
                        f"found {position!r}"
                    ) from None
    return None


def estimate_station(
    chunks: Iterable[PointCloud],
    *,
    cell_m: float = 1.0,
    search_radius_m: float = 3.0,
    height_m: float = 1.7,
    slab_m: float = 0.5,
) -> Station:
    """Estimate a static scan's station from its points (see the module docstring).

    Memory grows with the occupied XY cells, not with the points.

    Raises:
        CubeMapError: no points, or non-positive parameters.
    """
    if not (cell_m > 0 and search_radius_m > 0 and slab_m > 0):
        raise CubeMapError(
            f"estimate_station: expected cell_m and search_radius_m > 0, found "
            f"{cell_m}, {search_radius_m}"
        )
    # Cells are counted per horizontal slab of ``slab_m``: a facade stacks many points in
    # few XY cells but spreads them over many slabs; the ground near the tripod does not.
    keys = np.empty((0, 3), np.int64)
    counts = np.empty(0, np.int64)
    low_z = np.empty(0, np.float64)
    for chunk in chunks:
        if chunk.n_points == 0:
            continue
        cells = np.column_stack(
            [
                np.floor(chunk.xyz[:, :2] / cell_m).astype(np.int64),
                np.floor(chunk.xyz[:, 2] / slab_m).astype(np.int64),
            ]
        )
        keys = np.concatenate([keys, cells])
        counts = np.concatenate([counts, np.ones(chunk.n_points, np.int64)])
        low_z = np.concatenate([low_z, chunk.xyz[:, 2]])
        keys, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        counts = np.bincount(inverse, weights=counts, minlength=keys.shape[0]).astype(np.int64)
        merged_z = np.full(keys.shape[0], np.inf)
        np.minimum.at(merged_z, inverse, low_z)
        low_z = merged_z
    if keys.shape[0] == 0:
        raise CubeMapError("estimate_station: expected points, found an empty scan")
    xy_keys, column = np.unique(keys[:, :2], axis=0, return_inverse=True)
    column = column.reshape(-1)
    slab_counts = np.zeros(xy_keys.shape[0], np.int64)
    np.maximum.at(slab_counts, column, counts)
    column_z = np.full(xy_keys.shape[0], np.inf)
    np.minimum.at(column_z, column, low_z)
    keys, counts, low_z = xy_keys, slab_counts, column_z
    origin = keys.min(axis=0)
    shape = keys.max(axis=0) - origin + 1
    grid = np.zeros(tuple(shape + 2), np.float64)
    local = keys - origin + 1
    grid[local[:, 0], local[:, 1]] = counts
    smooth = np.zeros_like(grid)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            smooth += np.roll(np.roll(grid, dx, axis=0), dy, axis=1)
    best = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    best_xy = (np.asarray(best, np.float64) - 1 + origin + 0.5) * cell_m
    centres = (keys + 0.5) * cell_m
    near = np.hypot(*(centres - best_xy).T) <= search_radius_m
    weights = counts[near].astype(np.float64)
    xy = (centres[near] * weights[:, None]).sum(axis=0) / weights.sum()
    ground = float(np.percentile(low_z[near], 10))
    return (float(xy[0]), float(xy[1]), ground + height_m)


def resolve_station(
    points_path: str | Path,
    *,
    station: Station | None = None,
    chunks: Iterable[PointCloud] | None = None,
) -> StationSource:
    """The station of a scan: ``station`` if given, else its sidecar's, else estimated.

    ``chunks`` are the scan's points for the estimate (default: read ``points_path``).
    """
    if station is not None:
        return StationSource(tuple(float(v) for v in station), "option")  # type: ignore[arg-type]
    found = read_sidecar_station(points_path)
    if found is not None:
        return StationSource(found, "sidecar")
    if chunks is None:
        from semantic3d.io.formats import iter_points

        chunks = iter_points(points_path, sibling_labels=False)
    return StationSource(estimate_station(chunks), "estimated")
