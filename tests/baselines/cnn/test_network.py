"""The network's shape and size, and the error without the extra."""

from __future__ import annotations

import importlib
import sys

import pytest
import torch

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.network import build_network, count_parameters
from semantic3d.core.errors import MissingExtraError


def test_the_paper_network_has_5_6_million_parameters_and_8_outputs() -> None:
    config = CnnConfig()
    network = build_network(config.cubes, config.network).eval()
    # 5 paths x (448 + 13,856 + 55,360) + 2560*2048 + 2048 + 2048*8 + 8
    assert count_parameters(network) == 5_609_640
    assert network.head[0].in_features == 5 * 64 * 2**3
    with torch.inference_mode():
        logits = network(torch.zeros(2, 5, 16, 16, 16))
    assert logits.shape == (2, 8)


def test_importing_the_network_without_torch_names_the_extra(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now fails
    monkeypatch.delitem(sys.modules, "semantic3d.baselines.cnn.network")
    with pytest.raises(MissingExtraError, match=r"pip install 'semantic3d\[torch\]'"):
        importlib.import_module("semantic3d.baselines.cnn.network")
