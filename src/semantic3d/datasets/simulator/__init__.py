"""A static terrestrial laser scanner simulator producing labelled Semantic3D-like scans.

Procedural scenes (:func:`build_scene`: village, street, square, railway) are made of
exact-intersection primitives over a quadric terrain; a panoramic scanner on a tripod
sweeps them (:func:`simulate_scan`), giving the properties the semantic3D paper stresses:
density falling with range², occlusion shadows, long range, little noise (millimetres here), smeared
moving objects (scanning artefacts), and scans of hundreds of millions of points streamed
in chunks. :func:`simulate` writes ``.txt`` / ``.labels`` files and a JSON sidecar.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
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

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "MAX_STATIONS": "semantic3d.datasets.simulator.scene",
        "Motion": "semantic3d.datasets.simulator.primitives",
        "Primitive": "semantic3d.datasets.simulator.primitives",
        "RayHits": "semantic3d.datasets.simulator.scanner",
        "ScanPlan": "semantic3d.datasets.simulator.scanner",
        "Scanner": "semantic3d.datasets.simulator.scanner",
        "Scene": "semantic3d.datasets.simulator.scene",
        "SceneBuilder": "semantic3d.datasets.simulator.scenes.builder",
        "SceneName": "semantic3d.datasets.simulator.scenes",
        "Shape": "semantic3d.datasets.simulator.primitives",
        "SimulationConfigError": "semantic3d.datasets.simulator.errors",
        "SimulationResult": "semantic3d.datasets.simulator.simulation",
        "Station": "semantic3d.datasets.simulator.scene",
        "StationScan": "semantic3d.datasets.simulator.simulation",
        "Surface": "semantic3d.datasets.simulator.primitives",
        "Terrain": "semantic3d.datasets.simulator.terrain",
        "Zone": "semantic3d.datasets.simulator.terrain",
        "ZoneShape": "semantic3d.datasets.simulator.terrain",
        "build_scene": "semantic3d.datasets.simulator.scenes",
        "cast_rays": "semantic3d.datasets.simulator.scanner",
        "compile_scene": "semantic3d.datasets.simulator.scene",
        "plan_scan": "semantic3d.datasets.simulator.scanner",
        "simulate": "semantic3d.datasets.simulator.simulation",
        "simulate_scan": "semantic3d.datasets.simulator.scanner",
    },
)
