"""Simulated scans on a Dask cluster: one task per station.

Each worker builds the scene from its name and seed, scans one station and writes its
``.txt`` / ``.labels`` through the same
:func:`semantic3d.datasets.simulator.simulation.simulate_station` the files of
:func:`semantic3d.datasets.simulator.simulate` come from; this process gathers the
stations in order and writes the sidecar. The files are byte for byte those of the
single-process run. The output folder must be visible to the workers.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.scanner import Scanner, validate_n_points
from semantic3d.datasets.simulator.scenes import SceneName, build_scene, validate_scene_name
from semantic3d.datasets.simulator.simulation import (
    SimulationResult,
    StationScan,
    prepare_output_folder,
    simulate_station,
    validate_stations,
    write_sidecar,
)
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE
from semantic3d.scale.cluster import DaskCluster, MapProgress, map_items

__all__ = ["simulate_on_cluster"]


def simulate_on_cluster(
    scene: SceneName | str,
    *,
    out: Path,
    n_points: int,
    cluster: DaskCluster | None,
    stations: int = 1,
    seed: int = 0,
    scanner: Scanner = Scanner(),
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: MapProgress | None = None,
) -> SimulationResult:
    """What :func:`~semantic3d.datasets.simulator.simulate` does, a station per task.

    ``cluster`` None runs the tasks in this process. ``progress(stations_done, total)``.

    Raises:
        SimulationConfigError: a bad scene name, point count, station count or folder.
        ClusterError: a task failed on every try.
    """
    name = validate_scene_name(scene)
    n_points = validate_n_points(n_points)
    stations = validate_stations(stations)
    built = build_scene(name, seed=seed)  # cheap: the layout, not the compiled scene
    if stations > len(built.stations):
        raise SimulationConfigError(
            f"stations: scene {built.name!r} has {len(built.stations)}, found {stations}"
        )
    out = Path(out)
    prepare_output_folder(out)
    task = partial(
        _station_task,
        scene=name.value,
        out=out,
        n_points=n_points,
        seed=seed,
        scanner=scanner,
        chunk_size=chunk_size,
    )
    scans = tuple(map_items(cluster, task, range(1, stations + 1), progress=progress))
    result = SimulationResult(
        built.name, int(seed), n_points, scanner, scans, out / f"{built.name}.json"
    )
    write_sidecar(result)
    return result


def _station_task(
    station: int,
    *,
    scene: str,
    out: Path,
    n_points: int,
    seed: int,
    scanner: Scanner,
    chunk_size: int,
) -> StationScan:
    return simulate_station(
        scene,
        station,
        out=out,
        n_points=n_points,
        seed=seed,
        scanner=scanner,
        chunk_size=chunk_size,
    )
