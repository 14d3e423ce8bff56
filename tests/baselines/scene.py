"""A small generated street scene: ground, buildings, trees, bushes, cars, low walls.

Each object is sampled on its surfaces (volumes for tree crowns and bushes) at roughly
``spacing_m``, with centimetre noise, so the classes differ by shape and size the way the
benchmark's do. Two seeds give two different layouts: train on one, test on the other.
"""

from __future__ import annotations

import numpy as np

from semantic3d.core import PointCloud

MAN_MADE_TERRAIN, NATURAL_TERRAIN, HIGH_VEGETATION, LOW_VEGETATION = 1, 2, 3, 4
BUILDINGS, HARD_SCAPE, CARS = 5, 6, 8


def _box_surface(
    rng: np.random.Generator, low: np.ndarray, high: np.ndarray, spacing: float, *, floor: bool
) -> np.ndarray:
    size = high - low
    faces = []
    for axis in range(3):
        other = [a for a in range(3) if a != axis]
        area = size[other[0]] * size[other[1]]
        n = max(int(area / spacing**2), 4)
        for side in (0, 1):
            if axis == 2 and side == 0 and not floor:
                continue
            pts = low + rng.uniform(0, 1, (n, 3)) * size
            pts[:, axis] = low[axis] + side * size[axis]
            faces.append(pts)
    return np.concatenate(faces)


def _ball(rng: np.random.Generator, centre: np.ndarray, radii: np.ndarray, n: int) -> np.ndarray:
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return centre + direction * radii * rng.uniform(0, 1, (n, 1)) ** (1 / 3)


def make_street_scene(
    seed: int, *, size_m: float = 40.0, spacing_m: float = 0.15, with_colour: bool = False
) -> PointCloud:
    """A labelled scene of about ``(size_m / spacing_m)**2 * 1.6`` points."""
    rng = np.random.default_rng(seed)
    parts: list[tuple[np.ndarray, int]] = []
    n_ground = int((size_m / spacing_m) ** 2)
    ground = rng.uniform(0, size_m, (n_ground, 3))
    ground[:, 2] = 0.02 * rng.normal(size=n_ground)
    grass = ground[:, 1] > 0.75 * size_m
    ground[grass, 2] += 0.05 * rng.normal(size=int(grass.sum()))
    parts.append((ground[~grass], MAN_MADE_TERRAIN))
    parts.append((ground[grass], NATURAL_TERRAIN))
    for _ in range(2):  # buildings along the far side of the road
        x0 = rng.uniform(0, size_m - 12)
        low = np.array([x0, rng.uniform(2, 6), 0.0])
        high = low + np.array([rng.uniform(8, 12), rng.uniform(5, 8), rng.uniform(6, 12)])
        parts.append((_box_surface(rng, low, high, spacing_m, floor=False), BUILDINGS))
    for _ in range(4):  # trees: a trunk and a crown
        base = np.array([rng.uniform(2, size_m - 2), rng.uniform(16, 28), 0.0])
        height = rng.uniform(2.5, 4)
        trunk_n = int(height / spacing_m * 6)
        angle = rng.uniform(0, 2 * np.pi, trunk_n)
        trunk = np.column_stack(
            [
                base[0] + 0.15 * np.cos(angle),
                base[1] + 0.15 * np.sin(angle),
                rng.uniform(0, height, trunk_n),
            ]
        )
        crown = _ball(rng, base + np.array([0, 0, height + 1.5]), np.array([2.0, 2.0, 1.8]), 2500)
        parts.append((np.concatenate([trunk, crown]), HIGH_VEGETATION))
    for _ in range(6):  # bushes on the grass
        centre = np.array([rng.uniform(1, size_m - 1), rng.uniform(0.78, 0.97) * size_m, 0.35])
        parts.append((_ball(rng, centre, np.array([0.8, 0.8, 0.4]), 500), LOW_VEGETATION))
    for _ in range(4):  # cars on the road
        low = np.array([rng.uniform(0, size_m - 5), rng.uniform(12, 15), 0.2])
        high = low + np.array([4.2, 1.8, 1.3])
        parts.append((_box_surface(rng, low, high, spacing_m, floor=False), CARS))
    for _ in range(3):  # low walls
        low = np.array([rng.uniform(0, size_m - 8), rng.uniform(9, 10.5), 0.0])
        high = low + np.array([rng.uniform(5, 8), 0.25, 0.9])
        parts.append((_box_surface(rng, low, high, spacing_m / 2, floor=False), HARD_SCAPE))
    xyz = np.concatenate([p for p, _ in parts])
    labels = np.concatenate([np.full(len(p), value, np.uint8) for p, value in parts])
    xyz = xyz + 0.01 * rng.normal(size=xyz.shape) + np.array([1000.0, 2000.0, 50.0])
    order = rng.permutation(len(xyz))
    rgb = None
    if with_colour:
        rgb = rng.integers(0, 256, (len(xyz), 3))
    return PointCloud.from_arrays(
        np.round(xyz[order], 3),
        intensity=rng.integers(-2000, 2000, len(xyz)),
        rgb=None if rgb is None else rgb[order],
        labels=labels[order],
    )
