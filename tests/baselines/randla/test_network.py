"""The network's shape and size, batches of stacked sub-clouds, and the error without the extra."""

from __future__ import annotations

import importlib
import sys

import numpy as np
import pytest
import torch

from semantic3d.baselines.randla.config import NetworkConfig, preset_config
from semantic3d.baselines.randla.levels import build_levels, stack_levels
from semantic3d.baselines.randla.network import build_network, count_parameters
from semantic3d.core.errors import MissingExtraError


def _mlp(c_in: int, c_out: int) -> int:  # linear without bias + batch norm's scale and shift
    return c_in * c_out + 2 * c_out


def _expected_parameters(n_inputs: int, n_classes: int, config: NetworkConfig) -> int:
    """The paper's layers counted by hand (supplementary material, figure 7)."""
    total = _mlp(n_inputs, config.feature_channels)
    d_in = config.feature_channels
    for d in config.channels:
        attentive = d * d + _mlp(d, d // 2) + d * d + _mlp(d, d)
        aggregation = _mlp(10, d // 2) + _mlp(d // 2, d // 2) + attentive
        total += _mlp(d_in, d // 2) + aggregation + _mlp(d, 2 * d) + _mlp(d_in, 2 * d)
        d_in = 2 * d
    total += _mlp(d_in, d_in)
    skips = [2 * config.channels[max(level - 1, 0)] for level in range(len(config.channels))]
    for skip in reversed(skips):
        total += _mlp(skip + d_in, skip)
        d_in = skip
    return total + _mlp(d_in, 64) + _mlp(64, 32) + 32 * n_classes + n_classes


@pytest.mark.parametrize(
    ("preset", "n_inputs", "expected"), [("cpu", 3, 321_439), ("paper", 6, None)]
)
def test_parameter_counts_follow_the_paper_layers(
    preset: str, n_inputs: int, expected: int | None
) -> None:
    config = preset_config(preset).network
    network = build_network(n_inputs, 7, config)
    assert count_parameters(network) == _expected_parameters(n_inputs, 7, config)
    if expected is not None:
        assert count_parameters(network) == expected
    # the paper's Semantic3D network: five layers, ~5 M parameters
    if preset == "paper":
        assert config.channels == (16, 64, 128, 256, 512) and config.ratios == (4, 4, 4, 4, 2)
        assert 4_900_000 < count_parameters(network) < 5_100_000


def _cloud(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-3, 3, (n, 3)).astype(np.float32)


def test_logits_per_point_and_stacked_clouds_equal_separate_ones() -> None:
    config = NetworkConfig(k_neighbours=8, channels=(8, 16), ratios=(4, 4))
    torch.manual_seed(0)
    network = build_network(3, 5, config).eval()
    clouds = [_cloud(1, 300), _cloud(2, 57)]
    levels = [build_levels(c, k=8, ratios=config.ratios, device="cpu") for c in clouds]
    assert levels[0].sizes == (300, 75, 19) and levels[1].sizes == (57, 15, 4)
    with torch.inference_mode():
        stacked = network(
            torch.from_numpy(np.concatenate(clouds)), stack_levels(clouds, levels, device="cpu")
        )
        alone = [
            network(torch.from_numpy(c), stack_levels([c], [lv], device="cpu"))
            for c, lv in zip(clouds, levels, strict=True)
        ]
    assert stacked.shape == (357, 5)
    torch.testing.assert_close(stacked, torch.cat(alone), rtol=1e-4, atol=1e-5)


def test_gradients_reach_every_parameter() -> None:
    config = NetworkConfig(k_neighbours=4, channels=(8, 16), ratios=(4, 2))
    network = build_network(3, 4, config).train()
    cloud = _cloud(3, 200)
    batch = stack_levels(
        [cloud], [build_levels(cloud, k=4, ratios=config.ratios, device="cpu")], device="cpu"
    )
    network(torch.from_numpy(cloud), batch).logsumexp(dim=1).mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in network.parameters())


def test_importing_the_network_without_torch_names_the_extra(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now fails
    monkeypatch.delitem(sys.modules, "semantic3d.baselines.randla.network")
    with pytest.raises(MissingExtraError, match=r"pip install 'semantic3d\[torch\]'"):
        importlib.import_module("semantic3d.baselines.randla.network")
