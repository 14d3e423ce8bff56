"""A static terrestrial laser scanner simulator producing labelled Semantic3D-like scans.

Procedural scenes (:func:`build_scene`: village, street, square, railway) are made of
exact-intersection primitives over a quadric terrain; a panoramic scanner on a tripod
sweeps them (:func:`simulate_scan`), giving the properties the semantic3D paper stresses:
density falling with range², occlusion shadows, long range, millimetre noise, smeared
moving objects (scanning artefacts), and scans of hundreds of millions of points streamed
in chunks. :func:`simulate` writes ``.txt`` / ``.labels`` files and a JSON sidecar.
"""

from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.datasets.simulator.primitives import Motion, Primitive, Shape, Surface
from semantic3d.datasets.simulator.scanner import (
    RayHits,
    Scanner,
    ScanPlan,
    cast_rays,
    plan_scan,
    simulate_scan,
)
from semantic3d.datasets.simulator.scene import MAX_STATIONS, Scene, Station, compile_scene
from semantic3d.datasets.simulator.scenes import SceneName, build_scene
from semantic3d.datasets.simulator.scenes.builder import SceneBuilder
from semantic3d.datasets.simulator.simulation import SimulationResult, StationScan, simulate
from semantic3d.datasets.simulator.terrain import Terrain, Zone, ZoneShape

__all__ = [
    "MAX_STATIONS",
    "Motion",
    "Primitive",
    "RayHits",
    "ScanPlan",
    "Scanner",
    "Scene",
    "SceneBuilder",
    "SceneName",
    "Shape",
    "SimulationConfigError",
    "SimulationResult",
    "Station",
    "StationScan",
    "Surface",
    "Terrain",
    "Zone",
    "ZoneShape",
    "build_scene",
    "cast_rays",
    "compile_scene",
    "plan_scan",
    "simulate",
    "simulate_scan",
]
