"""Point-centred cubes made by the torch kernel equal the compiled kernel's, bit for bit:
on the CPU device here, on CUDA under the ``gpu`` marker."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic3d.baselines.cnn.cubes import CentringError, build_occupancy, compute_cubes
from semantic3d.baselines.cnn.point_cubes_torch import (
    DevicePointCubes,
    pack_cubes,
    unpack_cubes,
)
from semantic3d.core.errors import ShapeError

DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=[
            pytest.mark.gpu,
            pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"),
        ],
    ),
]


def adversarial_tile(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points on voxel borders (a lattice of 1/16 m), duplicates, a cell of thousands of
    points, a plane tilted against all three axes (cells keep every row: the kernel's
    longest scans), a volume; queries among them, on borders, and far from everything."""
    rng = np.random.default_rng(seed)
    lattice = rng.integers(-32, 32, (1200, 3)) * 0.0625
    dense = rng.uniform(0, 1, (2500, 3)) * [2.0, 2.0, 0.5]
    crowded = rng.uniform(0, 1, (2500, 3)) * 0.9 + [-3.0, 1.0, 0.0]
    u, v = rng.uniform(0, 1, (2, 3000))
    on = (u + v > 0.5) & (u + v <= 1.5)
    tilted = np.column_stack([2 + u[on], -4 + v[on], 1.5 - u[on] - v[on]])
    points = np.concatenate([lattice, dense, crowded, tilted, lattice[:150]])
    queries = np.concatenate(
        [
            points[::53],
            rng.integers(-32, 32, (12, 3)) * 0.03125,  # on the borders of every scale
            tilted[:5],
            [[60.0, 60.0, 0.0], [-40.0, 3.0, 9.0]],  # empty neighbourhoods
        ]
    )
    return points, queries


@pytest.mark.parametrize("device", DEVICES)
def test_device_cubes_equal_the_compiled_ones_on_adversarial_tiles(
    device: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    scanned: list[int] = []  # the most rows a pair scans in each call
    scan_rows = DevicePointCubes._scan_rows

    def spy(
        self: DevicePointCubes, pairs: torch.Tensor, first: torch.Tensor, *rest: object
    ) -> object:
        scanned.append(int(rest[0].max()))  # type: ignore[attr-defined]
        return scan_rows(self, pairs, first, *rest)

    monkeypatch.setattr(DevicePointCubes, "_scan_rows", spy)
    origin = np.array([-4.0, -4.0, -2.0])
    sizes = (0.125, 0.25, 1.0)
    points, queries = adversarial_tile(0)
    occupancy = build_occupancy(points, origin=origin, voxel_sizes_m=sizes, centring="point")
    for size, budget, block in ((8, None, None), (8, 5000, 7), (16, None, 64)):
        expected = compute_cubes(occupancy, queries, cube_voxels=size, centring="point")
        held = DevicePointCubes(
            occupancy, device=device, cube_voxels=size, pair_budget=budget, query_block=block
        )
        cubes = held.fill_points(queries)
        assert cubes.device.type == device and cubes.dtype == torch.float32
        np.testing.assert_array_equal(cubes.cpu().numpy(), expected)
        as_bytes = held.fill_points(queries[:9], dtype=torch.uint8)
        np.testing.assert_array_equal(as_bytes.cpu().numpy(), expected[:9].astype(np.uint8))
    assert 0.02 < expected.mean() < 0.5
    assert not expected[-2:].any()  # far from every point
    assert max(scanned) > 96  # rounds past rows 8-32 and 32-128 were needed


@pytest.mark.parametrize("device", DEVICES)
def test_device_cubes_of_random_and_georeferenced_tiles(device: str) -> None:
    rng = np.random.default_rng(1)
    sizes = (0.025, 0.05, 0.1, 0.2, 0.4)  # the paper's scales
    shift = np.array([870_000.0, 6_617_000.0, 120.0])  # whole 0.4 m cells, as the origin
    local = np.concatenate(
        [rng.uniform(0, 4, (3000, 3)) * [1, 1, 0.3], np.round(rng.uniform(0, 4, (500, 3)), 2)]
    )
    for origin, points in ((np.zeros(3), local), (shift, local + shift)):
        occupancy = build_occupancy(points, origin=origin, voxel_sizes_m=sizes, centring="point")
        queries = points[::70]
        expected = compute_cubes(occupancy, queries, cube_voxels=16, centring="point")
        held = DevicePointCubes(occupancy, device=device, cube_voxels=16)
        np.testing.assert_array_equal(held.fill_points(queries).cpu().numpy(), expected)
        # A tile's cells and fractions sent once, batches filled from slices of them.
        cells, fractions = held.anchors(queries)
        half = cells.shape[0] // 2
        second = held.fill(cells[half:], fractions[half:])
        np.testing.assert_array_equal(second.cpu().numpy(), expected[half:])


def test_empty_occupancy_and_no_queries() -> None:
    sizes = (0.1, 0.4)
    empty = build_occupancy(
        np.empty((0, 3)), origin=np.zeros(3), voxel_sizes_m=sizes, centring="point"
    )
    queries = np.random.default_rng(2).uniform(0, 2, (5, 3))
    cubes = DevicePointCubes(empty, device="cpu", cube_voxels=8).fill_points(queries)
    assert cubes.shape == (5, 2, 8, 8, 8) and not cubes.any()
    occupancy = build_occupancy(queries, origin=np.zeros(3), voxel_sizes_m=sizes, centring="point")
    none = DevicePointCubes(occupancy, device="cpu", cube_voxels=8).fill_points(np.empty((0, 3)))
    assert none.shape == (0, 2, 8, 8, 8)


def test_bit_packing_matches_numpy_and_round_trips() -> None:
    cubes = (np.random.default_rng(3).uniform(size=(6, 3, 8, 8, 8)) < 0.2).astype(np.float32)
    packed = pack_cubes(torch.from_numpy(cubes))
    np.testing.assert_array_equal(
        packed.numpy(), np.packbits(cubes.reshape(6, -1).astype(np.uint8), axis=1)
    )
    back = unpack_cubes(packed, (3, 8, 8, 8), dtype=torch.float32)
    np.testing.assert_array_equal(back.numpy(), cubes)


def test_bad_input_is_refused() -> None:
    points = np.random.default_rng(4).uniform(0, 1, (20, 3))
    corner = build_occupancy(points, origin=np.zeros(3), voxel_sizes_m=(0.1,))
    with pytest.raises(CentringError, match="expected cell summaries for point-centred"):
        DevicePointCubes(corner, device="cpu", cube_voxels=8)
    held = DevicePointCubes(
        build_occupancy(points, origin=np.zeros(3), voxel_sizes_m=(0.1,), centring="point"),
        device="cpu",
        cube_voxels=8,
    )
    with pytest.raises(ShapeError, match=r"cells: expected \(n, 1, 3\), found \(4, 2, 3\)"):
        held.fill(np.zeros((4, 2, 3), np.int64), np.zeros((4, 2, 3)))
    with pytest.raises(ShapeError, match=r"xyz: expected \(n, 3\) coordinates, found \(4, 2\)"):
        held.fill_points(np.zeros((4, 2)))
