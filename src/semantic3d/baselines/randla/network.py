"""RandLA-Net (Hu et al., CVPR 2020) in plain PyTorch, on stacked sub-clouds.

Written from the paper (section 3 and its supplementary network details):

- **Local spatial encoding** (LocSE): for point ``p_i`` and each of its ``k`` neighbours
  ``p_ik``, ``r_ik = MLP(p_i ⊕ p_ik ⊕ (p_i − p_ik) ⊕ ‖p_i − p_ik‖)`` (10 → d/2 channels),
  concatenated with the neighbour's features.
- **Attentive pooling**: a shared linear layer scores every channel of every neighbour,
  a softmax over the ``k`` neighbours turns scores into weights, the weighted sum is the
  point's feature, followed by a shared MLP.
- **Dilated residual block**: MLP (d/2), LocSE + attentive pooling (d/2), LocSE +
  attentive pooling (d), MLP (2d), added to a shortcut MLP (2d) of the input, leaky ReLU.
  Two aggregations in a row see the neighbours' neighbours: the receptive field grows
  from k to about k².
- **Encoder–decoder**: a per-point layer (8 channels), then per layer a dilated residual
  block and random sampling (features max-pooled over each kept point's neighbours);
  an MLP at the bottom; per layer, nearest-neighbour upsampling, concatenation with the
  encoder's features of that level (skip link) and an MLP; then 64, 32, dropout and the
  class logits.

Every MLP is a linear layer, batch normalisation and a leaky ReLU (slope 0.2), applied to
the last dimension of ``(points, channels)`` or ``(points, k, channels)`` tensors, so any
number of stacked points of any number of sub-clouds goes through in one call
(:class:`~semantic3d.baselines.randla.levels.LevelBatch`).
"""

from __future__ import annotations

from typing import Any

from semantic3d.baselines.randla.config import NetworkConfig
from semantic3d.core.errors import require

torch: Any = require("torch", "torch")
nn: Any = torch.nn
functional: Any = torch.nn.functional

__all__ = [
    "RandlaNet",
    "build_network",
    "count_parameters",
    "skip_channels",
]

_SLOPE = 0.2


class SharedMlp(nn.Module):
    """Linear layer (no bias: the normalisation's shift is one), batch norm, leaky ReLU."""

    def __init__(self, c_in: int, c_out: int, *, activation: bool = True) -> None:
        super().__init__()
        self.linear = nn.Linear(c_in, c_out, bias=False)
        self.norm = nn.BatchNorm1d(c_out, momentum=0.1, eps=1e-3)
        self.activation = activation

    def forward(self, x: Any) -> Any:
        shape = x.shape
        y = self.norm(self.linear(x.reshape(-1, shape[-1])))
        if self.activation:
            y = functional.leaky_relu(y, _SLOPE)
        return y.reshape(*shape[:-1], y.shape[-1])


def _gather(features: Any, indices: Any) -> Any:
    """``features[indices]`` for ``(n, c)`` features and ``(m, k)`` indices: ``(m, k, c)``."""
    m, k = indices.shape
    return features.index_select(0, indices.reshape(-1)).reshape(m, k, features.shape[-1])


def relative_positions(xyz: Any, neighbours: Any) -> Any:
    """``(n, k, 10)``: distance, offset, the point and its neighbour, per neighbour."""
    around = _gather(xyz, neighbours)
    centre = xyz.unsqueeze(1).expand_as(around)
    offset = centre - around
    distance = torch.linalg.vector_norm(offset, dim=-1, keepdim=True)
    return torch.cat([distance, offset, centre, around], dim=-1)


class AttentivePooling(nn.Module):
    """Per-channel attention weights over the ``k`` neighbours, their weighted sum, an MLP."""

    def __init__(self, channels: int, c_out: int) -> None:
        super().__init__()
        self.score = nn.Linear(channels, channels, bias=False)
        self.mlp = SharedMlp(channels, c_out)

    def forward(self, features: Any) -> Any:  # (n, k, c) -> (n, c_out)
        weights = torch.softmax(self.score(features), dim=1)
        return self.mlp((features * weights).sum(dim=1))


class LocalAggregation(nn.Module):
    """Two rounds of local spatial encoding and attentive pooling (d/2 -> d channels)."""

    def __init__(self, d_out: int) -> None:
        super().__init__()
        half = d_out // 2
        self.scale_positions = nn.BatchNorm1d(10, momentum=0.1, eps=1e-3, affine=False)
        self.encode_1 = SharedMlp(10, half)
        self.pool_1 = AttentivePooling(d_out, half)
        self.encode_2 = SharedMlp(half, half)
        self.pool_2 = AttentivePooling(d_out, d_out)

    def forward(self, xyz: Any, features: Any, neighbours: Any) -> Any:
        positions = relative_positions(xyz, neighbours)
        shape = positions.shape
        positions = self.scale_positions(positions.reshape(-1, 10)).reshape(shape)
        encoded = self.encode_1(positions)
        pooled = self.pool_1(torch.cat([_gather(features, neighbours), encoded], dim=-1))
        encoded = self.encode_2(encoded)
        return self.pool_2(torch.cat([_gather(pooled, neighbours), encoded], dim=-1))


class DilatedResidualBlock(nn.Module):
    """MLP, local aggregation, MLP, plus a shortcut: ``d_in`` -> ``2 d_out`` channels."""

    def __init__(self, d_in: int, d_out: int) -> None:
        super().__init__()
        self.reduce = SharedMlp(d_in, d_out // 2)
        self.aggregate = LocalAggregation(d_out)
        self.expand = SharedMlp(d_out, 2 * d_out, activation=False)
        self.shortcut = SharedMlp(d_in, 2 * d_out, activation=False)

    def forward(self, xyz: Any, features: Any, neighbours: Any) -> Any:
        aggregated = self.aggregate(xyz, self.reduce(features), neighbours)
        return functional.leaky_relu(self.expand(aggregated) + self.shortcut(features), _SLOPE)


def skip_channels(config: NetworkConfig) -> list[int]:
    """Channels of the encoder's outputs at levels ``0..L-1`` (the decoder's skip links):
    level 0 keeps the first block's output, level ``l > 0`` the pooled output of block
    ``l - 1``."""
    return [2 * config.channels[max(level - 1, 0)] for level in range(config.n_layers)]


class RandlaNet(nn.Module):
    """RandLA-Net: ``forward(features, batch)`` -> ``(points, n_classes)`` logits.

    Args:
        n_inputs: input channels per point (local xyz, then intensity and colour).
        n_classes: classes predicted.
        config: the network's layers.
    """

    def __init__(self, n_inputs: int, n_classes: int, config: NetworkConfig) -> None:
        super().__init__()
        self.n_inputs = n_inputs
        self.n_classes = n_classes
        self.first = SharedMlp(n_inputs, config.feature_channels)
        encoders = []
        d_in = config.feature_channels
        for d_out in config.channels:
            encoders.append(DilatedResidualBlock(d_in, d_out))
            d_in = 2 * d_out
        self.encoders = nn.ModuleList(encoders)
        self.bottom = SharedMlp(d_in, d_in)
        decoders = []
        for skip in reversed(skip_channels(config)):
            decoders.append(SharedMlp(skip + d_in, skip))
            d_in = skip
        self.decoders = nn.ModuleList(decoders)
        self.head = nn.Sequential(
            SharedMlp(d_in, 64),
            SharedMlp(64, 32),
            nn.Dropout(config.dropout),
            nn.Linear(32, n_classes),
        )

    def forward(self, features: Any, batch: Any) -> Any:
        """Logits of every level-0 point of ``batch`` (a ``LevelBatch``)."""
        x = self.first(features)
        skips = []
        for level, encoder in enumerate(self.encoders):
            encoded = encoder(batch.xyz[level], x, batch.neighbours[level])
            if level == 0:
                skips.append(encoded)
            # random sampling: each kept point takes the maximum over its neighbourhood
            around = batch.neighbours[level].index_select(0, batch.pool[level])
            x = _gather(encoded, around).amax(dim=1)
            if level + 1 < len(self.encoders):
                skips.append(x)
        x = self.bottom(x)
        for step, decoder in enumerate(self.decoders):
            level = len(self.decoders) - 1 - step
            upsampled = x.index_select(0, batch.up[level])
            x = decoder(torch.cat([skips[level], upsampled], dim=-1))
        return self.head(x)


def build_network(n_inputs: int, n_classes: int, config: NetworkConfig) -> RandlaNet:
    """A new network (weights from torch's generator)."""
    return RandlaNet(n_inputs, n_classes, config)


def count_parameters(network: Any) -> int:
    """Trainable parameters of ``network``."""
    return int(sum(p.numel() for p in network.parameters() if p.requires_grad))
