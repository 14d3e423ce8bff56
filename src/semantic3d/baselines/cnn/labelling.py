"""Labelling a tile's points: the next batch's cubes are made while the network classifies.

A producer thread (:class:`~semantic3d.baselines.common.pipeline.Prefetched`, two batches ahead) makes the cubes of
each batch; the caller's thread runs the network (:class:`~.inference.InferenceNetwork`)
and gathers class indices on the device, read back once per tile.

- On a CUDA device the cubes are born there: point-centred by
  :class:`~.point_cubes_torch.DevicePointCubes` (the tile's summaries and its points'
  cells and fractions go to the device once, each batch's cubes are filled there),
  corner-centred by :class:`~.cubes_torch.DeviceOccupancy`, on the producer's own stream.
  No float32 cube crosses the bus.
- On a CPU the compiled kernels (:mod:`.point_cubes`, :mod:`.cubes`) fill a ring of host
  buffers on all cores (numba's thread pool) while torch's threads run the network.

Both give every batch the exact cubes of :func:`~.cubes.compute_cubes`, so the labels do
not depend on the path (tested).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.cnn.config import CubeConfig
from semantic3d.baselines.cnn.cubes import (
    Occupancy,
    compute_corner_cells,
    compute_cubes,
    fill_cubes,
)
from semantic3d.baselines.cnn.inference import InferenceNetwork
from semantic3d.baselines.common.pipeline import Prefetched
from semantic3d.core.errors import require

torch: Any = require("torch", "torch")

__all__ = ["label_tile_points"]

_DEPTH = 2
"""Batches the producer may run ahead."""


def label_tile_points(
    network: InferenceNetwork,
    xyz: NDArray[np.float64],
    occupancy: Occupancy,
    *,
    cubes: CubeConfig,
    device_cubes: bool | None = None,
) -> NDArray[np.int64]:
    """Class indices of ``(n, 3)`` float64 points whose neighbourhood ``occupancy`` holds.

    Args:
        network: the network on its device (its ``batch_size`` sets the batches).
        xyz: the points.
        occupancy: the tile and its halo (:func:`~.cubes.build_occupancy`).
        cubes: the cubes' configuration.
        device_cubes: make the cubes with the torch kernels on the network's device;
            default: on a CUDA device only (on a CPU the compiled kernels are faster).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape[0] == 0:
        return np.empty(0, np.int64)
    on_device = network.device.type == "cuda" if device_cubes is None else device_cubes
    index = _classify(network, xyz, occupancy, cubes, on_device, precise=False)
    if index is None:  # a float16 overflow somewhere in the tile: float32 decides
        index = _classify(network, xyz, occupancy, cubes, on_device, precise=True)
        assert index is not None  # float32 logits are not checked
    return index


def _classify(
    network: InferenceNetwork,
    xyz: NDArray[np.float64],
    occupancy: Occupancy,
    cubes: CubeConfig,
    on_device: bool,
    *,
    precise: bool,
) -> NDArray[np.int64] | None:
    n = xyz.shape[0]
    batch = network.batch_size
    dtype = torch.float32 if precise else network.dtype
    if on_device:

        def produce() -> Iterator[tuple[int, Any]]:
            return _device_batches(xyz, occupancy, cubes, batch, network.device, dtype)
    else:

        def produce() -> Iterator[tuple[int, Any]]:
            return _host_batches(xyz, occupancy, cubes, batch)

    out = torch.empty(n, dtype=torch.int64, device=network.device)
    finite = torch.ones((), dtype=torch.bool, device=network.device)
    with Prefetched(produce, depth=_DEPTH, device=network.device, name="cubes") as batches:
        for begin, filled in batches:
            index, ok = network.classify(filled, precise=precise)
            out[begin : begin + filled.shape[0]] = index
            finite &= ok
    result = out.cpu().numpy()  # the tile's one wait for the device
    if not precise and not bool(finite):
        return None
    return result


def _device_batches(
    xyz: NDArray[np.float64],
    occupancy: Occupancy,
    cubes: CubeConfig,
    batch: int,
    device: Any,
    dtype: Any,
) -> Iterator[tuple[int, Any]]:
    """Cubes filled on ``device`` from the tile's occupancy, sent there once."""
    size = cubes.cube_voxels
    if cubes.centring == "point":
        from semantic3d.baselines.cnn.point_cubes_torch import DevicePointCubes

        held = DevicePointCubes(occupancy, device=device, cube_voxels=size)
        cells, fractions = held.anchors(xyz)
        for begin in range(0, xyz.shape[0], batch):
            stop = begin + batch
            yield begin, held.fill(cells[begin:stop], fractions[begin:stop], dtype=dtype)
        return
    from semantic3d.baselines.cnn.cubes_torch import DeviceOccupancy

    corners_held = DeviceOccupancy(occupancy, device=device, cube_voxels=size)
    corners = torch.as_tensor(
        compute_corner_cells(
            xyz, origin=occupancy.origin, voxel_sizes_m=cubes.voxel_sizes_m, cube_voxels=size
        ),
        device=device,
    )
    for begin in range(0, xyz.shape[0], batch):
        yield begin, corners_held.fill(corners[begin : begin + batch], dtype=dtype)


def _host_batches(
    xyz: NDArray[np.float64], occupancy: Occupancy, cubes: CubeConfig, batch: int
) -> Iterator[tuple[int, Any]]:
    """Cubes filled by the compiled kernels into a ring of host buffers: a buffer is
    filled again only once the consumer is done with it (``_DEPTH`` queued, one being
    classified, one being filled)."""
    size = cubes.cube_voxels
    n = xyz.shape[0]
    rows = min(batch, n)
    ring = [
        np.empty((rows, cubes.n_scales, size, size, size), np.float32)
        for _ in range(min(_DEPTH + 2, -(-n // rows)))
    ]
    corners = None
    if cubes.centring == "corner":
        corners = compute_corner_cells(
            xyz, origin=occupancy.origin, voxel_sizes_m=cubes.voxel_sizes_m, cube_voxels=size
        )
    for number, begin in enumerate(range(0, n, batch)):
        stop = min(begin + batch, n)
        buffer = ring[number % len(ring)][: stop - begin]
        if corners is None:
            filled = compute_cubes(
                occupancy, xyz[begin:stop], cube_voxels=size, centring="point", out=buffer
            )
        else:
            filled = fill_cubes(occupancy, corners[begin:stop], cube_voxels=size, out=buffer)
        yield begin, torch.from_numpy(filled)
