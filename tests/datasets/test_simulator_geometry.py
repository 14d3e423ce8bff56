"""Exact intersections, porous volumes, motion and labels of the simulator, checked against
an independent numpy reference (point-in-solid tests marched and bisected along each ray)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from semantic3d.core import class_by_name
from semantic3d.datasets.simulator import (
    Motion,
    Primitive,
    Scanner,
    Scene,
    Shape,
    Station,
    Surface,
    Terrain,
    Zone,
    ZoneShape,
    cast_rays,
    simulate_scan,
)
from semantic3d.datasets.simulator.kernels import HIT_GROUND, NO_HIT
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE

GREY = Surface((128, 128, 128), 0.5)
FLAT = Terrain((0.0, 0.0, 0.0, 0.0, 0.0, 0.0), 2, GREY)
FAR = Station(1, (0.0, 0.0, 500.0))


def contains(
    prim: Primitive, points: NDArray[np.float64], time_s: float = 0.0
) -> NDArray[np.bool_]:
    """Reference point-in-solid test (scipy rotation, plain numpy)."""
    centre = np.asarray(prim.center, np.float64)
    if prim.motion is not None:
        centre = centre + np.asarray(prim.motion.direction) * prim.motion.offset_at(time_s)
    rotation = Rotation.from_euler("ZYX", [prim.yaw_rad, prim.pitch_rad, prim.roll_rad])
    x, y, z = rotation.inv().apply(points - centre).T
    hx, hy, hz = prim.half_size
    in_box = (np.abs(x) <= hx) & (np.abs(y) <= hy) & (np.abs(z) <= hz)
    if prim.shape is Shape.BOX:
        return in_box
    if prim.shape is Shape.GABLE:
        return in_box & (z <= hz - 2.0 * hz * np.abs(y) / hy)
    if prim.shape is Shape.CYLINDER:
        return ((x / hx) ** 2 + (y / hy) ** 2 <= 1.0) & (np.abs(z) <= hz)
    return (x / hx) ** 2 + (y / hy) ** 2 + (z / hz) ** 2 <= 1.0


def reference_distance(
    prim: Primitive, origin: NDArray[np.float64], direction: NDArray[np.float64], t_max: float
) -> float:
    """First entry into ``prim`` along the ray: 2 mm march, then bisection; inf if none."""
    ts = np.arange(0.0, t_max, 0.002)
    inside = contains(prim, origin + ts[:, None] * direction)
    if not inside.any():
        return math.inf
    k = int(np.argmax(inside))
    lo, hi = ts[max(k - 1, 0)], ts[k]
    for _ in range(40):
        mid = (lo + hi) / 2
        if contains(prim, (origin + mid * direction)[None])[0]:
            hi = mid
        else:
            lo = mid
    return hi


def single(prim: Primitive) -> Scene:
    return Scene("one", FLAT, (prim,), (FAR,))


SHAPES = [
    Primitive(Shape.BOX, (1.0, 2.0, 3.0), (2.0, 0.5, 1.5), 5, GREY, yaw_rad=0.7, pitch_rad=0.2),
    Primitive(
        Shape.CYLINDER,
        (-1.0, 0.5, 2.0),
        (0.8, 1.4, 2.5),
        3,
        GREY,
        yaw_rad=0.3,
        roll_rad=math.pi / 2,
    ),
    Primitive(
        Shape.ELLIPSOID,
        (0.0, 0.0, 4.0),
        (3.0, 1.5, 2.0),
        4,
        GREY,
        yaw_rad=1.1,
        pitch_rad=0.4,
        roll_rad=-0.3,
    ),
    Primitive(Shape.GABLE, (2.0, -1.0, 6.0), (5.0, 4.0, 1.5), 5, GREY, yaw_rad=-0.5),
]


@pytest.mark.parametrize("prim", SHAPES, ids=lambda p: p.shape.name)
def test_distances_match_the_reference_solid(prim: Primitive) -> None:
    rng = np.random.default_rng(int(prim.shape))
    lo, hi = prim.bounds()
    centre, span = (lo + hi) / 2, (hi - lo) / 2
    scene = single(prim)
    disagreements = 0
    for _ in range(120):
        direction_to = rng.normal(size=3)
        origin = centre + 12.0 * direction_to / np.linalg.norm(direction_to)
        target = centre + rng.uniform(-1.3, 1.3, 3) * span  # some rays miss
        direction = (target - origin) / np.linalg.norm(target - origin)
        hits = cast_rays(scene, origin, direction[None], scanner=Scanner(min_range_m=0.0))
        expected = reference_distance(prim, origin, direction, 30.0)
        got = float(hits.distance_m[0])
        ground = hits.primitive[0] == HIT_GROUND
        if math.isinf(expected) or ground:
            disagreements += int(hits.primitive[0] == 0)
            continue
        assert hits.primitive[0] == 0 and hits.labels[0] == prim.label
        assert got == pytest.approx(expected, abs=1e-6)
    assert disagreements <= 2  # grazing chords thinner than the 2 mm reference march


def test_terrain_hits_lie_on_the_height_quadric() -> None:
    terrain = Terrain((0.3, 0.01, -0.02, 2e-4, -1e-4, 3e-4), 2, GREY)
    scene = Scene("relief", terrain, (), (FAR,))
    rng = np.random.default_rng(1)
    origin = np.array([3.0, -4.0, float(terrain.height_at(3.0, -4.0)) + 1.7])
    azimuth = rng.uniform(0, 2 * np.pi, 500)
    elevation = rng.uniform(-1.2, -0.01, 500)
    directions = np.stack(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ],
        1,
    )
    hits = cast_rays(scene, origin, directions, scanner=Scanner(min_range_m=0.0, max_range_m=1e4))
    assert (hits.primitive == HIT_GROUND).all()
    points = origin + hits.distance_m[:, None] * directions
    np.testing.assert_allclose(
        points[:, 2], terrain.height_at(points[:, 0], points[:, 1]), atol=1e-9
    )
    up = cast_rays(scene, origin, [[0.3, 0.1, 0.5]], scanner=Scanner(max_range_m=1e4))
    assert up.primitive[0] == NO_HIT and math.isinf(up.distance_m[0])


def test_porous_volume_lets_through_exp_minus_density_times_depth() -> None:
    density, depth = 1.5, 1.0
    crown = Primitive(
        Shape.BOX, (10.0, 0.0, 5.0), (depth / 2, 50.0, 50.0), 3, GREY, density_per_m=density
    )
    directions = np.tile([1.0, 0.0, 0.0], (40_000, 1))
    hits = cast_rays(single(crown), (0.0, 0.0, 5.0), directions, seed=3)
    through = np.mean(hits.primitive == NO_HIT)
    assert through == pytest.approx(math.exp(-density * depth), abs=0.01)
    inside = hits.distance_m[hits.primitive == 0]
    assert inside.min() >= 9.5 and inside.max() <= 10.5  # returns from within the volume
    again = cast_rays(single(crown), (0.0, 0.0, 5.0), directions, seed=3)
    np.testing.assert_array_equal(again.distance_m, hits.distance_m)


def test_moving_primitive_is_where_its_motion_puts_it() -> None:
    motion = Motion((1.0, 0.0, 0.0), 2.0, 10.0)
    walker = Primitive(Shape.BOX, (0.0, 10.0, 1.0), (0.3, 0.3, 1.0), 7, GREY, motion=motion)
    scene = single(walker)
    down_y = [[0.0, 1.0, 0.0]]
    for time_s, offset in ((0.0, 0.0), (2.5, 5.0), (5.0, 10.0), (7.5, 5.0), (12.5, 5.0)):
        assert motion.offset_at(time_s) == pytest.approx(offset)
        at = cast_rays(scene, (offset, 0.0, 1.0), down_y, times_s=time_s)
        assert at.primitive[0] == 0 and at.distance_m[0] == pytest.approx(9.7)
        away = cast_rays(scene, (offset + 2.0, 0.0, 1.0), down_y, times_s=time_s)
        assert away.primitive[0] == NO_HIT


def test_scan_labels_are_those_of_the_solid_or_zone_each_ray_hit() -> None:
    zones = (
        Zone(ZoneShape.RECTANGLE, (0.0, 0.0), (30.0, 3.0), 1, GREY),
        Zone(ZoneShape.ELLIPSE, (8.0, 8.0), (4.0, 2.5), 2, GREY, yaw_rad=0.4),
        Zone(ZoneShape.RECTANGLE, (-6.0, 6.0), (2.0, 5.0), 1, GREY, yaw_rad=-0.3),
    )
    terrain = Terrain((0.0, 0.01, 0.0, 0.0, 0.0, 1e-4), 2, GREY, zones)
    prims = (
        Primitive(Shape.BOX, (8.0, -6.0, 1.0), (2.0, 1.0, 1.5), 5, GREY, yaw_rad=0.5),
        Primitive(Shape.GABLE, (8.0, -6.0, 3.5), (2.4, 1.4, 1.0), 5, GREY, yaw_rad=0.5),
        Primitive(
            Shape.CYLINDER,
            (-5.0, -5.0, 0.3),
            (0.35, 0.35, 0.3),
            8,
            GREY,
            yaw_rad=0.2,
            roll_rad=math.pi / 2,
        ),
        Primitive(Shape.ELLIPSOID, (-3.0, 9.0, 4.0), (2.0, 2.0, 2.5), 3, GREY, density_per_m=1.5),
        Primitive(Shape.CYLINDER, (-3.0, 9.0, 0.7), (0.2, 0.2, 0.8), 3, GREY),
        Primitive(Shape.BOX, (12.0, 3.0, 0.5), (0.2, 4.0, 0.8), 6, GREY, yaw_rad=0.1),
        Primitive(Shape.ELLIPSOID, (-10.0, -2.0, 0.4), (1.0, 0.8, 0.6), 4, GREY, density_per_m=4.0),
    )
    scene = Scene("labels", terrain, prims, (Station(1, (0.0, 0.0, 1.7)),))
    scanner = Scanner(range_noise_m=0.0, max_range_m=40.0)
    cloud = next(
        simulate_scan(
            scene,
            scene.stations[0],
            n_points=60_000,
            seed=5,
            scanner=scanner,
            chunk_size=DEFAULT_CHUNK_SIZE,
        )
    )
    origin = np.array(scene.stations[0].position)
    rays = (cloud.xyz - origin) / np.linalg.norm(cloud.xyz - origin, axis=1, keepdims=True)
    beyond = cloud.xyz + 1e-5 * rays  # just past a surface return, inside what was hit
    x, y, z = cloud.xyz.T
    on_ground = np.abs(z - terrain.height_at(x, y)) < 1e-7  # noise-free: exactly on it
    expected = np.zeros(cloud.n_points, np.uint8)
    expected[on_ground] = terrain.label_at(x[on_ground], y[on_ground])
    claimed = np.zeros(cloud.n_points, np.int64)
    for prim in prims:  # a return from a porous volume lies inside it
        inside = contains(prim, cloud.xyz if prim.density_per_m > 0 else beyond) & ~on_ground
        expected[inside] = prim.label
        claimed += inside
    assert (claimed[~on_ground] == 1).all()
    np.testing.assert_array_equal(cloud.labels, expected)
    assert set(np.unique(cloud.labels)) == {1, 2, 3, 4, 5, 6, 8}
    assert class_by_name("cars").value in cloud.labels


@settings(max_examples=60, deadline=None)
@given(
    angles=st.lists(
        st.tuples(*[st.floats(-7.0, 7.0, allow_nan=False)] * 3), min_size=0, max_size=12
    ),
    moving=st.lists(st.booleans(), min_size=12, max_size=12),
)
def test_packed_primitives_hold_each_primitives_own_rotation_and_bounds(
    angles: list[tuple[float, float, float]], moving: list[bool]
) -> None:
    """The table packed column by column holds, bit for bit, what each primitive gives
    alone (its rotation transposed, its bounds with its motion), and its other fields."""
    from semantic3d.datasets.simulator.primitives import (
        P_CENTER,
        P_MOTION_DIR,
        P_PATH,
        P_REFLECTANCE,
        P_RGB,
        P_WORLD_TO_LOCAL,
        pack_primitives,
    )

    surface = Surface((10, 200, 30), 0.25, 0.3, 0.5, 2.0)
    prims = [
        Primitive(
            Shape(number % len(Shape)),
            (number * 1.5, -2.0, 0.25 * number),
            (0.5 + number, 0.25, 1.0 + 0.1 * number),
            1 + number % 8,
            surface,
            yaw,
            pitch,
            roll,
            motion=Motion((0.6, 0.8, 0.0), 1.5, 3.0, 0.5) if moving[number] else None,
        )
        for number, (yaw, pitch, roll) in enumerate(angles)
    ]
    packed = pack_primitives(prims)
    assert packed.n_primitives == len(prims)
    for row, prim in enumerate(prims):
        rotation = prim.rotation()
        lower, upper = prim.bounds(rotation)
        params = packed.params[row]
        assert params[P_WORLD_TO_LOCAL : P_WORLD_TO_LOCAL + 9].tobytes() == rotation.T.tobytes()
        assert packed.lower[row].tobytes() == lower.tobytes()
        assert packed.upper[row].tobytes() == upper.tobytes()
        assert params[P_CENTER : P_CENTER + 3].tolist() == list(prim.center)
        assert params[P_RGB : P_RGB + 3].tolist() == [10, 200, 30]
        assert params[P_REFLECTANCE] == 0.25
        direction = params[P_MOTION_DIR : P_MOTION_DIR + 3].tolist()
        assert direction == ([0.6, 0.8, 0.0] if prim.motion else [0.0, 0.0, 0.0])
        assert params[P_PATH] == (3.0 if prim.motion else 0.0)
        assert packed.shapes[row] == int(prim.shape) and packed.labels[row] == prim.label
