"""Occupancy cubes on a torch device (the GPU path): the corner-centred lookup of
:mod:`.cubes` in torch.

Corner-centred cubes only. Point-centred cubes (``centring = "point"``, the default) need
each occupied cell's orthant summary, a list of a different length per cell scanned per
query, which has no clean batched form in torch; a model with point-centred cubes fills
them with the compiled CPU kernel (:mod:`.point_cubes`, all host cores) and sends them to
the device, where the network runs (:meth:`~.model.CnnModel.label_points`).

The tile's sorted keys and the points' corner cells (integers, computed in float64 on the
host by :func:`~semantic3d.baselines.cnn.cubes.compute_corner_cells`) go to the device;
every cube voxel's key is formed there and looked up with one ``torch.searchsorted`` per
scale, so the cubes are born on the device and never cross the bus. The result equals
:func:`~semantic3d.baselines.cnn.cubes.fill_cubes` exactly (integers only).

Needs the ``[torch]`` extra.
"""

from __future__ import annotations

from typing import Any

from semantic3d.core.errors import require

torch: Any = require("torch", "torch")

from semantic3d.baselines.cnn.cubes import Occupancy  # noqa: E402
from semantic3d.core.errors import ShapeError  # noqa: E402
from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET  # noqa: E402

__all__ = ["DeviceOccupancy"]


class DeviceOccupancy:
    """An :class:`~semantic3d.baselines.cnn.cubes.Occupancy` held on a torch device.

    Args:
        occupancy: the occupied cells of a tile and its halo.
        device: where to hold them and fill cubes (``"cuda"``, ``"cpu"``).
        cube_voxels: ``C``.
    """

    def __init__(self, occupancy: Occupancy, *, device: Any, cube_voxels: int) -> None:
        self.device = torch.device(device)
        self.cube_voxels = cube_voxels
        self.keys = [torch.as_tensor(k, device=self.device) for k in occupancy.keys]
        axis = torch.arange(cube_voxels, device=self.device, dtype=torch.int64)
        grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1)
        self._offsets = grid.reshape(-1, 3)  # x, y, z of each cube voxel, row-major

    def fill(self, corners: Any, *, dtype: Any = None) -> Any:
        """``(n, n_scales, C, C, C)`` cubes (``dtype``, default float32) of ``(n, n_scales, 3)``
        int64 corner cells (a tensor or array, on any device)."""
        corners = torch.as_tensor(corners, device=self.device, dtype=torch.int64)
        n_scales = len(self.keys)
        if corners.ndim != 3 or tuple(corners.shape[1:]) != (n_scales, 3):
            raise ShapeError(f"corners: expected (n, {n_scales}, 3), found {tuple(corners.shape)}")
        size = self.cube_voxels
        out = torch.zeros(
            (corners.shape[0], n_scales, size, size, size),
            dtype=dtype or torch.float32,
            device=self.device,
        )
        for scale, keys in enumerate(self.keys):
            if keys.numel() == 0:
                continue
            cells = corners[:, scale, None, :] + self._offsets + CELL_OFFSET  # (n, C^3, 3)
            packed = (
                (cells[..., 0] << (2 * CELL_BITS)) | (cells[..., 1] << CELL_BITS) | cells[..., 2]
            )
            found = torch.searchsorted(keys, packed).clamp_(max=keys.numel() - 1)
            hit = keys[found] == packed
            out[:, scale] = hit.reshape(-1, size, size, size).to(out.dtype)
        return out
