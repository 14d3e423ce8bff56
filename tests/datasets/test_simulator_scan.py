"""Properties of simulated scans: density against range, occlusion shadows, range noise,
the solved resolution, chunking invariance, intensity and the smear of moving objects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semantic3d.core import PointCloud
from semantic3d.datasets.simulator import (
    Motion,
    Primitive,
    Scanner,
    Scene,
    Shape,
    Station,
    Surface,
    Terrain,
    plan_scan,
    simulate_scan,
)

GREY = Surface((128, 128, 128), 0.5)
FLAT = Terrain((0.0, 0.0, 0.0, 0.0, 0.0, 0.0), 1, GREY)
HEIGHT = 1.7
STATION = Station(1, (0.0, 0.0, HEIGHT))


def scan(
    scene: Scene,
    n_points: int,
    *,
    scanner: Scanner = Scanner(),
    seed: int = 0,
    chunk_size: int = 1 << 20,
) -> PointCloud:
    return PointCloud.concatenate(
        list(
            simulate_scan(
                scene,
                scene.stations[0],
                n_points=n_points,
                seed=seed,
                scanner=scanner,
                chunk_size=chunk_size,
            )
        )
    )


def slope(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def test_density_falls_with_range_squared_on_open_ground() -> None:
    scanner = Scanner(max_range_m=60.0, range_noise_m=0.0)
    cloud = scan(Scene("open", FLAT, (), (STATION,)), 150_000, scanner=scanner)
    ranges = np.hypot(cloud.xyz[:, 0], cloud.xyz[:, 1])
    edges = np.geomspace(5.0, 50.0, 9)
    counts = np.histogram(ranges, edges)[0].astype(float)
    centres = np.sqrt(edges[1:] * edges[:-1])
    # Points per metre of range fall as range⁻² (one angular step covers ~r²Δ/H metres).
    assert slope(centres, counts / np.diff(edges)) == pytest.approx(-2.0, abs=0.1)
    # Per square metre seen face-on (areal density over the cosine of incidence) too ...
    areal = counts / (np.pi * np.diff(edges**2))
    incidence = HEIGHT / np.hypot(centres, HEIGHT)
    assert slope(centres, areal / incidence) == pytest.approx(-2.0, abs=0.1)
    # ... so on the ground itself it falls faster still: grazing incidence adds range⁻¹.
    assert slope(centres, areal) == pytest.approx(-3.0, abs=0.15)


def test_density_on_a_facing_wall_is_one_per_step_squared_at_range_squared() -> None:
    roof = Station(1, (0.0, 0.0, 20.0))  # high up, so the window below stays on the wall
    for distance in (8.0, 24.0):
        wall = Primitive(Shape.BOX, (distance + 0.5, 0.0, 20.0), (0.5, 40.0, 20.0), 5, GREY)
        scene = Scene("wall", FLAT, (wall,), (roof,))
        plan = plan_scan(scene, roof, n_points=100_000)
        cloud = scan(scene, 100_000)
        half = distance / 8.0  # the same ±7° window: about 27 × 27 beams at both ranges
        patch = (np.abs(cloud.xyz[:, 1]) < half) & (np.abs(cloud.xyz[:, 2] - 20.0) < half)
        assert (cloud.labels[patch] == 5).all()
        density = np.count_nonzero(patch) / (2.0 * half) ** 2
        expected = 1.0 / (plan.azimuth_step_rad * plan.elevation_step_rad * distance**2)
        assert density == pytest.approx(expected, rel=0.08)


def test_no_returns_in_the_shadow_behind_a_wall() -> None:
    wall = Primitive(Shape.BOX, (10.0, 0.0, 1.0), (0.2, 3.0, 1.0), 6, GREY, yaw_rad=0.2)
    scanner = Scanner(max_range_m=40.0)
    walled = scan(Scene("walled", FLAT, (wall,), (STATION,)), 150_000, scanner=scanner)
    open_ = scan(Scene("open", FLAT, (), (STATION,)), 150_000, scanner=scanner)

    def behind_wall(points: np.ndarray) -> np.ndarray:
        """Whether the segment scanner→point crosses the wall (an independent slab test)."""
        c, s = math.cos(0.2), math.sin(0.2)
        local = (points - wall.center) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        origin = (np.array(STATION.position) - wall.center) @ np.array(
            [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        )
        direction = local - origin
        t0, t1 = np.zeros(len(points)), np.full(len(points), 0.999)
        for axis, half in enumerate(wall.half_size):
            with np.errstate(divide="ignore", invalid="ignore"):
                a = (-half - origin[axis]) / direction[:, axis]
                b = (half - origin[axis]) / direction[:, axis]
            t0 = np.maximum(t0, np.minimum(a, b))
            t1 = np.minimum(t1, np.maximum(a, b))
        return t0 <= t1

    ground = walled.labels == 1
    assert np.count_nonzero(behind_wall(walled.xyz[ground])) == 0
    assert np.count_nonzero(behind_wall(open_.xyz)) > 500  # the shadow is not empty by chance
    assert np.count_nonzero(walled.labels == 6) > 500


def test_range_noise_has_the_configured_deviation_along_the_beam() -> None:
    scanner = Scanner(range_noise_m=0.004, max_range_m=30.0)
    cloud = scan(Scene("open", FLAT, (), (STATION,)), 50_000, scanner=scanner)
    offsets = cloud.xyz - np.array(STATION.position)
    measured = np.linalg.norm(offsets, axis=1)
    true_range = measured * HEIGHT / -offsets[:, 2]  # where the beam meets z = 0
    error = measured - true_range
    assert abs(error.mean()) < 0.0002
    assert error.std() == pytest.approx(0.004, rel=0.05)


@pytest.mark.parametrize("n_points", [20_000, 120_000])
def test_the_solved_resolution_gives_about_n_points(n_points: int) -> None:
    wall = Primitive(Shape.BOX, (15.0, 0.0, 3.0), (0.5, 10.0, 3.0), 5, GREY)
    scene = Scene("half", FLAT, (wall,), (STATION,))
    cloud = scan(scene, n_points)
    assert cloud.n_points == pytest.approx(n_points, rel=0.05)


def test_chunking_does_not_change_the_scan() -> None:
    crown = Primitive(Shape.ELLIPSOID, (6.0, 3.0, 4.0), (2.0, 2.0, 2.5), 3, GREY, density_per_m=1.2)
    scene = Scene("tree", FLAT, (crown,), (STATION,))
    chunks = list(simulate_scan(scene, STATION, n_points=30_000, seed=4, chunk_size=1000))
    assert all(c.n_points == 1000 for c in chunks[:-1]) and 0 < chunks[-1].n_points <= 1000
    whole = scan(scene, 30_000, seed=4, chunk_size=1 << 20)
    assert PointCloud.concatenate(chunks).equals(whole)
    assert not scan(scene, 30_000, seed=5).equals(whole)


def test_intensity_is_in_range_and_falls_with_incidence() -> None:
    cloud = scan(Scene("open", FLAT, (), (STATION,)), 40_000, scanner=Scanner(max_range_m=30.0))
    assert cloud.intensity.min() >= -2048 and cloud.intensity.max() <= 2047
    ranges = np.hypot(cloud.xyz[:, 0], cloud.xyz[:, 1])
    steep = cloud.intensity[ranges < 2.0].mean()
    grazing = cloud.intensity[(ranges > 15.0) & (ranges < 20.0)].mean()
    assert steep > grazing + 300


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_moving_object_is_smeared_by_its_speed_relative_to_the_sweep(direction: float) -> None:
    """The head turns at ω; a walker crossing the beam at v along the sweep is recorded
    ``ω / (ω - v/R)`` times its length (shorter when it walks against the sweep)."""
    distance, speed, half_length = 10.0, 0.2, 0.5
    sweep = 180.0
    omega = 2 * math.pi / sweep
    # Placed so that it crosses the beam in the middle of its segment, 90° into the sweep.
    motion = Motion((-direction, 0.0, 0.0), speed, 20.0, phase_m=10.0 - speed * sweep / 4)
    walker = Primitive(
        Shape.BOX,
        (direction * 10.0, distance, 1.0),
        (half_length, 0.2, 1.0),
        7,
        GREY,
        motion=motion,
    )
    scene = Scene("walker", FLAT, (walker,), (STATION,))
    cloud = scan(scene, 200_000, scanner=Scanner(sweep_duration_s=sweep, max_range_m=20.0))
    seen = cloud.xyz[cloud.labels == 7]
    assert len(seen) > 100
    recorded = seen[:, 0].max() - seen[:, 0].min()
    expected = 2 * half_length * omega / (omega - direction * speed / distance)
    assert recorded == pytest.approx(expected, rel=0.15)
