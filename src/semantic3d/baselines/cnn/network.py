"""DeepNet, the paper's 3D CNN: one VGG-like path per scale, two fully connected layers.

Per scale ``c(1,16) r m c(16,32) r m c(32,64) r m`` (3x3x3 convolutions, zero padding 1,
stride 1; 2x2x2 max pooling, stride 2); the paths' outputs are flattened and concatenated
(5 x 64 x 2^3 = 2560) into ``f(2560,2048) r d(0.5) f(2048,8)``. The soft-max is the loss's
(:class:`torch.nn.CrossEntropyLoss`); :meth:`DeepNet.forward` returns logits. With the
paper's values it has 5,609,640 parameters.

Needs the ``[torch]`` extra.
"""

from __future__ import annotations

from typing import Any

from semantic3d.core.classes import N_CLASSES
from semantic3d.core.errors import require

torch: Any = require("torch", "torch")
nn: Any = torch.nn

from semantic3d.baselines.cnn.config import CubeConfig, NetworkConfig  # noqa: E402

__all__ = ["DeepNet", "build_network", "count_parameters"]


class DeepNet(nn.Module):
    """The network of :mod:`semantic3d.baselines.cnn.network`.

    Args:
        n_scales: cubes per point.
        cube_voxels: voxels along a cube's edge (a multiple of 8).
        channels: output channels of the three convolutions of a path.
        hidden_units: width of the fully connected layer.
        dropout: dropout probability.
        n_classes: outputs (class indices 0..7 are label values 1..8).
    """

    def __init__(
        self,
        *,
        n_scales: int = 5,
        cube_voxels: int = 16,
        channels: tuple[int, ...] = (16, 32, 64),
        hidden_units: int = 2048,
        dropout: float = 0.5,
        n_classes: int = N_CLASSES,
    ) -> None:
        super().__init__()
        self.n_scales = n_scales
        self.cube_voxels = cube_voxels
        self.paths = nn.ModuleList(_path(channels) for _ in range(n_scales))
        flat = n_scales * channels[-1] * (cube_voxels // 8) ** 3
        self.head = nn.Sequential(
            nn.Linear(flat, hidden_units),
            nn.ReLU(inplace=True),
            nn.Dropout(dropout),
            nn.Linear(hidden_units, n_classes),
        )

    def forward(self, cubes: Any) -> Any:
        """Logits ``(n, n_classes)`` of ``(n, n_scales, C, C, C)`` occupancy cubes."""
        parts = [
            path(cubes[:, scale : scale + 1]).flatten(1) for scale, path in enumerate(self.paths)
        ]
        return self.head(torch.cat(parts, dim=1))


def _path(channels: tuple[int, ...]) -> Any:
    layers: list[Any] = []
    previous = 1
    for width in channels:
        layers += [
            nn.Conv3d(previous, width, kernel_size=3, stride=1, padding=1),
            nn.ReLU(inplace=True),
            nn.MaxPool3d(kernel_size=2, stride=2),
        ]
        previous = width
    return nn.Sequential(*layers)


def build_network(cubes: CubeConfig, network: NetworkConfig) -> DeepNet:
    """The network a configuration describes (weights from torch's current seed)."""
    return DeepNet(
        n_scales=cubes.n_scales,
        cube_voxels=cubes.cube_voxels,
        channels=network.channels,
        hidden_units=network.hidden_units,
        dropout=network.dropout,
    )


def count_parameters(module: Any) -> int:
    """Number of trainable parameters."""
    return int(sum(p.numel() for p in module.parameters() if p.requires_grad))
