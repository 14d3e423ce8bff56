"""The default scenes: every class in every scan, man-made terrain first, moving objects."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core import N_CLASSES, PointCloud, class_by_name
from semantic3d.datasets.simulator import (
    MAX_STATIONS,
    SceneName,
    SimulationConfigError,
    build_scene,
    compile_scene,
    plan_scan,
    simulate_scan,
)


@pytest.mark.parametrize("name", list(SceneName), ids=lambda n: n.value)
def test_every_station_of_a_default_scene_sees_all_classes(name: SceneName) -> None:
    scene = build_scene(name, seed=0)
    assert len(scene.stations) == MAX_STATIONS
    compiled = compile_scene(scene)
    man_made = class_by_name("man-made terrain").value
    artefacts = class_by_name("scanning artefacts").value
    for station in scene.stations:
        cloud = PointCloud.concatenate(list(simulate_scan(compiled, station, n_points=60_000)))
        assert cloud.labels is not None
        counts = np.bincount(cloud.labels, minlength=N_CLASSES + 1)
        assert counts[0] == 0
        assert (counts[1:] > 0).all(), f"{station.name}: classes missing in {counts.tolist()}"
        assert int(np.argmax(counts)) == man_made
        assert counts[artefacts] >= 5  # people and vehicles moving during the sweep


def test_scene_layout_is_fixed_by_the_seed() -> None:
    first, again, other = (build_scene("village", seed=s) for s in (3, 3, 4))
    assert first == again
    assert first != other


def test_stations_of_a_scene_overlap_a_little_and_stand_apart() -> None:
    for name in SceneName:
        scene = build_scene(name, seed=0)
        positions = np.array([s.position for s in scene.stations])
        gaps = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2)
        assert gaps[np.triu_indices(len(positions), 1)].min() > 15.0
        assert gaps.max() < 100.0  # close enough to share part of the scene
        for station in scene.stations:
            floor = scene.terrain.height_at(*station.position[:2])
            assert 1.5 <= station.position[2] - floor <= 2.0 or name is SceneName.RAILWAY


def test_scanner_is_not_inside_any_solid() -> None:
    for name in SceneName:
        scene = build_scene(name, seed=0)
        for station in scene.stations:
            for prim in scene.primitives:
                lo, hi = prim.bounds()
                assert not ((lo <= station.position) & (station.position <= hi)).all(), (
                    f"{name.value} {station.name} inside {prim.shape.name} at {prim.center}"
                )


def test_the_pilot_is_cheap_and_predicts_the_count() -> None:
    scene = build_scene("street", seed=1)
    plan = plan_scan(scene, scene.stations[1], n_points=50_000, seed=1)
    assert 0.3 < plan.return_ratio < 0.95
    assert plan.expected_points == pytest.approx(50_000, rel=0.03)
    assert plan.azimuth_step_rad == pytest.approx(plan.elevation_step_rad, rel=0.01)


def test_unknown_scene_and_bad_seed_are_rejected() -> None:
    with pytest.raises(
        SimulationConfigError, match="unknown scene 'moon': expected one of village"
    ):
        build_scene("moon")
    with pytest.raises(ValueError, match="seed: expected a non-negative integer, found -1"):
        build_scene("street", seed=-1)
