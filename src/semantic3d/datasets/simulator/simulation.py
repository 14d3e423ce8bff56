"""``simulate``: scan a scene from its stations and write Semantic3D files plus a sidecar.

Per station ``<scene>_station<k>.txt`` (``x y z intensity r g b``) and
``<scene>_station<k>.labels`` (one label value a line), in scene coordinates, and one
``<scene>.json`` sidecar holding the scene, the seed, the scanner and each station's pose
(position and yaw, and the 4×4 scanner-to-world matrix). Same arguments, same bytes.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from semantic3d import __version__
from semantic3d.core import N_CLASSES, class_by_value
from semantic3d.core.threads import iter_ahead, thread_budget
from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.scanner import (
    Scanner,
    ScanPlan,
    iter_sweep_blocks,
    plan_scan,
    validate_n_points,
)
from semantic3d.datasets.simulator.scene import (
    MAX_STATIONS,
    CompiledScene,
    Scene,
    Station,
    compile_scene,
)
from semantic3d.datasets.simulator.scenes import SceneName, build_scene
from semantic3d.io.ascii import open_ascii_writer
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, validate_chunk_size

logger = logging.getLogger(__name__)

SIDECAR_FORMAT = "semantic3d-simulation"
SIDECAR_VERSION = 1


@dataclass(frozen=True, slots=True)
class StationScan:
    """One written scan."""

    station: Station
    points_path: Path
    labels_path: Path
    n_points: int
    class_counts: tuple[int, ...]
    """Points per label value 0..8."""
    plan: ScanPlan


@dataclass(frozen=True, slots=True)
class SimulationResult:
    """What :func:`simulate` wrote."""

    scene: str
    seed: int
    n_points_requested: int
    scanner: Scanner
    scans: tuple[StationScan, ...]
    sidecar_path: Path

    @property
    def n_points(self) -> int:
        """Points written over all stations."""
        return sum(scan.n_points for scan in self.scans)


def simulate(
    scene: Scene | SceneName | str,
    *,
    out: Path,
    n_points: int,
    stations: int = 1,
    seed: int = 0,
    scanner: Scanner = Scanner(),
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[int, int], None] | None = None,
) -> SimulationResult:
    """Scan ``scene`` from its first ``stations`` stations, about ``n_points`` points each.

    A scene name builds the default scene with ``seed``; the same seed also drives the
    scanner noise. ``progress(points_done, points_expected)`` is called after each chunk.
    """
    n_points = validate_n_points(n_points)
    stations = validate_stations(stations)
    try:
        chunk_size = validate_chunk_size(chunk_size)
    except ValueError as exc:
        raise SimulationConfigError(str(exc)) from None
    built = scene if isinstance(scene, Scene) else build_scene(scene, seed=seed)
    if stations > len(built.stations):
        raise SimulationConfigError(
            f"stations: scene {built.name!r} has {len(built.stations)}, found {stations}"
        )
    out = Path(out)
    prepare_output_folder(out)
    compiled = compile_scene(built)
    chosen = built.stations[:stations]
    plans = [plan_scan(compiled, s, n_points=n_points, scanner=scanner, seed=seed) for s in chosen]
    expected = sum(plan.expected_points for plan in plans)
    scans = []
    done = 0
    for station, plan in zip(chosen, plans, strict=True):
        scan = _write_station(
            compiled,
            station,
            plan,
            out,
            seed=seed,
            scanner=scanner,
            chunk_size=chunk_size,
            progress=progress,
            done=done,
            expected=expected,
        )
        done += scan.n_points
        scans.append(scan)
        logger.info("%s: %d points", scan.points_path, scan.n_points)
    result = SimulationResult(
        built.name, int(seed), n_points, scanner, tuple(scans), out / f"{built.name}.json"
    )
    write_sidecar(result)
    return result


def simulate_station(
    scene: SceneName | str,
    station: int,
    *,
    out: Path,
    n_points: int,
    seed: int = 0,
    scanner: Scanner = Scanner(),
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[int, int], None] | None = None,
) -> StationScan:
    """Scan the default ``scene`` of ``seed`` from its station number ``station`` (from 1).

    The files are those :func:`simulate` writes for that station, byte for byte: a task
    of its own (e.g. on a cluster worker). :func:`write_sidecar` then writes the sidecar
    of the :class:`SimulationResult` gathered from the stations.
    """
    n_points = validate_n_points(n_points)
    station = validate_stations(station)
    try:
        chunk_size = validate_chunk_size(chunk_size)
    except ValueError as exc:
        raise SimulationConfigError(str(exc)) from None
    built = build_scene(scene, seed=seed)
    if station > len(built.stations):
        raise SimulationConfigError(
            f"stations: scene {built.name!r} has {len(built.stations)}, found {station}"
        )
    out = Path(out)
    compiled = compile_scene(built)
    chosen = built.stations[station - 1]
    plan = plan_scan(compiled, chosen, n_points=n_points, scanner=scanner, seed=seed)
    scan = _write_station(
        compiled,
        chosen,
        plan,
        out,
        seed=seed,
        scanner=scanner,
        chunk_size=chunk_size,
        progress=progress,
        done=0,
        expected=plan.expected_points,
    )
    logger.info("%s: %d points", scan.points_path, scan.n_points)
    return scan


def write_sidecar(result: SimulationResult) -> Path:
    """Write ``result``'s JSON sidecar to ``result.sidecar_path``; return that path."""
    result.sidecar_path.write_text(json.dumps(sidecar(result), indent=2) + "\n")
    return result.sidecar_path


def sidecar(result: SimulationResult) -> dict[str, object]:
    """The JSON sidecar's content (deterministic: no timestamps)."""
    return {
        "format": SIDECAR_FORMAT,
        "format_version": SIDECAR_VERSION,
        "generator": f"semantic3d {__version__}",
        "scene": result.scene,
        "seed": result.seed,
        "n_points_requested": result.n_points_requested,
        "coordinates": "scene frame, metres; scanner_to_world maps scanner coordinates to it",
        "scanner": asdict(result.scanner),
        "stations": [_station_record(scan) for scan in result.scans],
    }


def _station_record(scan: StationScan) -> dict[str, object]:
    station, plan = scan.station, scan.plan
    return {
        "name": station.name,
        "points": scan.points_path.name,
        "labels": scan.labels_path.name,
        "n_points": scan.n_points,
        "position_m": list(station.position),
        "yaw_rad": station.yaw_rad,
        "yaw_deg": math.degrees(station.yaw_rad),
        "scanner_to_world": station.matrix.tolist(),
        "start_time_s": station.start_time_s,
        "angular_step_deg": math.degrees(plan.azimuth_step_rad),
        "n_azimuth": plan.n_azimuth,
        "n_elevation": plan.n_elevation,
        "class_counts": {
            class_by_value(value).name: count for value, count in enumerate(scan.class_counts)
        },
    }


def validate_stations(stations: int) -> int:
    """``stations`` as an int, or :class:`SimulationConfigError` unless 1..MAX_STATIONS."""
    if isinstance(stations, bool) or int(stations) != stations or not 1 <= stations <= MAX_STATIONS:
        raise SimulationConfigError(
            f"stations: expected an integer in 1..{MAX_STATIONS}, found {stations!r}"
        )
    return int(stations)


def prepare_output_folder(out: Path) -> None:
    """Create ``out`` if needed and check files can be written there."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".semantic3d-write-probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise SimulationConfigError(
            f"{out}: expected a writable output folder, found {exc.strerror or exc}"
        ) from None


def _write_station(
    compiled: CompiledScene,
    station: Station,
    plan: ScanPlan,
    out: Path,
    *,
    seed: int,
    scanner: Scanner,
    chunk_size: int,
    progress: Callable[[int, int], None] | None,
    done: int,
    expected: int,
) -> StationScan:
    stem = f"{compiled.scene.name}_{station.name}"
    points_path, labels_path = out / f"{stem}.txt", out / f"{stem}.labels"
    # Blocks as they come: the file's bytes do not depend on how points are grouped. The
    # next block is cast and shaded on a thread of its own while this one is written.
    chunks = iter_ahead(
        iter_sweep_blocks(
            compiled, station, plan=plan, seed=seed, scanner=scanner, chunk_size=chunk_size
        ),
        # formatting and writing cost about a sixth of casting and shading: overlapping
        # them pays from 6 threads on, the writer taking a sixth of them
        consumer_threads=max(1, round(thread_budget() / 6)),
        min_threads=6,
        name="semantic3d-sweep",
    )
    with open_ascii_writer(points_path, labels_path=labels_path) as writer:
        for chunk in chunks:
            writer.write(chunk)
            if progress is not None:
                progress(done + writer.n_points, expected)
    counts = writer.label_counts[: N_CLASSES + 1]  # counted as the labels were formatted
    return StationScan(
        station, points_path, labels_path, writer.n_points, tuple(int(c) for c in counts), plan
    )
