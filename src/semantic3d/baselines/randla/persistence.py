"""Saving and loading a trained :class:`RandlaModel`.

One JSON header line (format and version, package and torch versions, resolved
configuration, label values, training scans, seed, batches trained, parameter count),
then the network's weights as a torch state dict, loaded with ``weights_only=True`` (no
arbitrary pickle). The header is checked before the weights are read: a file of another
kind or format version fails with a clear message. Weights are portable across torch
versions, so only the format version is enforced.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from semantic3d.baselines.common.modelfile import ModelFileError, ModelFileFormat
from semantic3d.baselines.randla.config import RandlaConfig, config_from_dict, config_to_dict
from semantic3d.baselines.randla.model import RandlaModel
from semantic3d.baselines.randla.network import build_network, count_parameters
from semantic3d.core.errors import ConfigError, require

torch: Any = require("torch", "torch")

FORMAT = "semantic3d-randla-model"
FORMAT_VERSION = 1
MODEL_FILE = ModelFileFormat(
    magic=b"S3DRLA1 ", kind="RandLA-Net model", name=FORMAT, version=FORMAT_VERSION
)
"""The baseline's kind of model file (the shared header, its own magic bytes)."""

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MODEL_FILE",
    "ModelFileError",
    "load_model",
    "read_model_header",
    "save_model",
]


def save_model(model: RandlaModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` atomically (parent folders created); returns the path."""
    header = {
        "package_version": model.package_version,
        "torch_version": str(torch.__version__),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "config": config_to_dict(model.config),
        "label_values": list(model.label_values),
        "training_scans": list(model.training_scans),
        "seed": model.seed,
        "n_batches_trained": model.n_batches_trained,
        "training_time_s": model.training_time_s,
        "n_parameters": count_parameters(model.network),
    }
    state = {k: v.detach().cpu() for k, v in model.network.state_dict().items()}

    def write(stream: IO[bytes]) -> None:
        torch.save(state, stream)

    return MODEL_FILE.write(path, header, write)


def read_model_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a model file, checked, without loading the weights."""
    return MODEL_FILE.read_header(path)


def load_model(path: str | Path, *, device: str = "cpu") -> RandlaModel:
    """Load a model saved by :func:`save_model`, ready on ``device``.

    Raises:
        ModelFileError: not a RandLA-Net model file, another format version, or weights
            that do not fit the configuration in its header.
        DeviceError: ``device`` is not one this machine has.
    """
    path = Path(path)
    with MODEL_FILE.open(path) as (header, stream):
        try:
            config: RandlaConfig = config_from_dict(header["config"], source=str(path))
            label_values = tuple(int(v) for v in header["label_values"])
        except (ConfigError, KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{path}: corrupt model header: {exc}") from exc
        try:
            state = torch.load(stream, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many kinds on a damaged payload
            raise ModelFileError(f"{path}: corrupt model weights: {exc}") from exc
    network = build_network(config.inputs.n_inputs, len(label_values), config.network)
    try:
        network.load_state_dict(state)
    except (RuntimeError, TypeError) as exc:
        raise ModelFileError(
            f"{path}: expected weights of the network its configuration describes: {exc}"
        ) from exc
    model = RandlaModel(
        network,
        config=config,
        label_values=label_values,
        training_scans=tuple(header["training_scans"]),
        seed=int(header["seed"]),
        n_batches_trained=int(header["n_batches_trained"]),
        training_time_s=float(header["training_time_s"]),
        package_version=str(header["package_version"]),
    )
    return model.to(device)
