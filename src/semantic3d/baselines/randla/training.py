"""Training RandLA-Net on sub-clouds drawn from the tiles of the training scans.

Each labelled scan is spilled once into a temporary tile store of whole voxels (the grid
prediction uses). Training runs in *rounds* of ``round_batches`` batches: a round draws
its ``round_batches x batch_size`` sub-cloud centres (``balanced``: each centre a point of
a class drawn in turn, uniformly over every scan; ``uniform``: a labelled point drawn
uniformly), reads each tile holding centres once with a halo of a window's half-width,
reduces it to voxels (labels by majority) and cuts a window about each centre
(:func:`~semantic3d.baselines.randla.blocks.window`: the width prediction uses, at most
``max_points`` voxels). Every sub-cloud is put in a random order (the network's random
sampling), rotated about z, mirrored, scaled and jittered, and its levels' neighbours are
searched. Its batches then go through Adam and a class-weighted cross-entropy. The scans'
voxels are never all held: memory is a round's sub-clouds and one tile.

Everything random comes from the seed: round ``r`` draws from ``numpy.random.default_rng
((seed, r))`` and the weights and dropout from torch's generator, whose state is saved in
every checkpoint; a resumed run gives the model of the run that was not interrupted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.baselines.common.device import resolve_device
from semantic3d.baselines.common.pipeline import Prefetched
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.baselines.common.training import (
    CheckpointError,
    TrainingProgress,
    TrainingProgressCallback,
    balanced_accuracy,
    load_checkpoint,
    save_checkpoint,
    training_classes,
)
from semantic3d.baselines.randla.blocks import local_coordinates, window
from semantic3d.baselines.randla.config import RandlaConfig, config_to_dict
from semantic3d.baselines.randla.levels import CloudLevels, build_levels, stack_levels
from semantic3d.baselines.randla.model import RandlaModel, grid_anchor, scan_grid
from semantic3d.baselines.randla.network import build_network
from semantic3d.baselines.randla.tile_voxels import read_tile_voxels
from semantic3d.core.classes import N_CLASSES
from semantic3d.core.errors import require
from semantic3d.core.pointcloud import PointCloud
from semantic3d.spatial.grid import TileKey
from semantic3d.spatial.store import TemporaryTileStore, TileStore

torch: Any = require("torch", "torch")

__all__ = ["CheckpointError", "TrainingProgress", "class_weights", "train_randla_model"]

logger = logging.getLogger(__name__)

_CHECKPOINT_FORMAT = 1
_WAIT_POLL_S = 0.25


@dataclass(slots=True)
class _Scan:
    name: str
    store: TileStore
    counts: NDArray[np.int64]  # (n_tiles, N_CLASSES + 1) points per tile and label value


@dataclass(frozen=True, slots=True)
class SubCloud:
    """One training sub-cloud, ready for a batch.

    Attributes:
        xyz: ``(n, 3)`` float32 local coordinates (augmented, in random order).
        features: ``(n, c)`` float32 network inputs.
        targets: ``(n,)`` int64 class indices (-1: not trained on).
        levels: its levels' neighbours.
    """

    xyz: NDArray[np.float32]
    features: NDArray[np.float32]
    targets: NDArray[np.int64]
    levels: CloudLevels


def class_weights(
    totals: NDArray[np.int64], classes: Sequence[int], kind: str
) -> NDArray[np.float32]:
    """Loss weight of each trained class from its share ``f`` of the training points:
    ``1 / (f + 0.02)`` (``inverse``), ``1 / sqrt(f)`` (``sqrt``) or 1 (``none``), scaled to
    a mean of 1.

    >>> class_weights(np.array([0, 90, 10]), [1, 2], "sqrt").round(3).tolist()
    [0.5, 1.5]
    """
    counts = np.array([totals[v] for v in classes], np.float64)
    share = counts / counts.sum()
    if kind == "inverse":
        weights = 1.0 / (share + 0.02)
    elif kind == "sqrt":
        weights = 1.0 / np.sqrt(np.maximum(share, 1e-12))
    else:
        weights = np.ones_like(share)
    return (weights / weights.mean()).astype(np.float32)


def train_randla_model(
    scans: Sequence[LabelledScan],
    *,
    config: RandlaConfig,
    device: str = "cpu",
    checkpoint: str | Path | None = None,
    resume: bool = False,
    workdir: str | Path | None = None,
    progress: TrainingProgressCallback | None = None,
) -> RandlaModel:
    """Train RandLA-Net on labelled scans with ``config.training``'s schedule.

    Args:
        scans: the labelled scans.
        config: the configuration (``training.n_batches`` sets the length of the run).
        device: ``cpu`` or ``cuda``.
        checkpoint: file to write every ``training.checkpoint_every`` batches (and to
            resume from).
        resume: continue from ``checkpoint`` (which must exist and match this run).
        workdir: scratch folder for the scans' tile stores (removed afterwards).
        progress: called after every batch, and while a round's sub-clouds are drawn.

    Raises:
        TrainingDataError: no scan, an empty scan, fewer than two classes, a listed class
            without points, or a scan without an input the configuration asks for.
        CheckpointError: ``resume`` without a usable checkpoint.
    """
    started = time.perf_counter()
    if not scans:
        raise TrainingDataError("training needs at least one labelled scan")
    if resume and (checkpoint is None or not Path(checkpoint).is_file()):
        raise CheckpointError(f"{checkpoint}: expected a checkpoint to resume from, found none")
    torch_device = resolve_device(device)
    training = config.training
    names = tuple(s.name for s in scans)
    with contextlib.ExitStack() as stack:
        tiled = [stack.enter_context(_tile_scan(scan, config, workdir)) for scan in scans]
        totals = sum((s.counts.sum(axis=0) for s in tiled), np.zeros(N_CLASSES + 1, np.int64))
        classes = training_classes(totals, training.classes, names)
        torch.manual_seed(training.seed)
        network = build_network(config.inputs.n_inputs, len(classes), config.network)
        network.to(torch_device)
        optimizer = torch.optim.Adam(network.parameters(), lr=training.learning_rate)
        done = 0
        if resume and checkpoint is not None:  # checked above: resume needs the file
            done = _load_checkpoint(Path(checkpoint), network, optimizer, config, names)
        weights = torch.from_numpy(class_weights(totals, classes, training.class_weights))
        loss_fn = torch.nn.CrossEntropyLoss(weight=weights.to(torch_device), ignore_index=-1)
        network.train()
        n_rounds = -(-training.n_batches // training.round_batches)
        start = done // training.round_batches

        def produce() -> Iterator[list[SubCloud]]:
            for index in range(start, n_rounds):
                length = min(
                    training.round_batches, training.n_batches - index * training.round_batches
                )
                yield _round_clouds(tiled, classes, config, index, length, torch_device)

        # round r + 1's sub-clouds are drawn on a thread of their own while round r trains
        rounds = stack.enter_context(
            Prefetched(produce, depth=1, device=torch_device, name="training-clouds")
        )
        while done < training.n_batches:
            round_index = done // training.round_batches
            first = round_index * training.round_batches
            n_round = min(training.round_batches, training.n_batches - first)
            clouds = _next_round(rounds, done, training.n_batches, progress)
            confusion = np.zeros((len(classes), len(classes)), np.int64)
            losses: list[float] = []
            for batch in range(done - first, n_round):
                members = clouds[batch * training.batch_size : (batch + 1) * training.batch_size]
                for group in optimizer.param_groups:
                    group["lr"] = training.learning_rate * training.lr_decay ** (
                        done // training.decay_every
                    )
                loss, predicted, target = _step(network, optimizer, loss_fn, members, torch_device)
                losses.append(loss)
                known = target >= 0
                np.add.at(confusion, (target[known], predicted[known]), 1)
                done += 1
                if progress is not None:
                    progress(
                        TrainingProgress(
                            done,
                            training.n_batches,
                            float(np.mean(losses)),
                            balanced_accuracy(confusion),
                        )
                    )
                if (
                    checkpoint is not None
                    and training.checkpoint_every
                    and done % training.checkpoint_every == 0
                    and done < training.n_batches
                ):
                    _save_checkpoint(Path(checkpoint), network, optimizer, done, config, names)
    network.eval().cpu()
    return RandlaModel(
        network,
        config=config,
        label_values=tuple(classes),
        training_scans=names,
        seed=training.seed,
        n_batches_trained=done,
        training_time_s=time.perf_counter() - started,
        package_version=__version__,
    )


def _next_round(
    rounds: Prefetched[list[SubCloud]],
    done: int,
    n_batches: int,
    progress: TrainingProgressCallback | None,
) -> list[SubCloud]:
    """The next round's sub-clouds (reported once as the ``"clouds"`` stage: drawn ahead,
    they are often there already)."""
    if progress is not None:
        progress(TrainingProgress(done, n_batches, math.nan, math.nan, "clouds"))
    while True:
        arrived, clouds = rounds.poll(_WAIT_POLL_S)
        if arrived:
            assert clouds is not None
            return clouds


def _step(
    network: Any, optimizer: Any, loss_fn: Any, clouds: Sequence[SubCloud], device: Any
) -> tuple[float, NDArray[np.int64], NDArray[np.int64]]:
    """One optimisation step on a batch of sub-clouds: its loss, predictions and targets."""
    batch = stack_levels([c.xyz for c in clouds], [c.levels for c in clouds], device=device)
    features = torch.from_numpy(np.concatenate([c.features for c in clouds])).to(device)
    target_np = np.concatenate([c.targets for c in clouds])
    target = torch.from_numpy(target_np).to(device)
    optimizer.zero_grad(set_to_none=True)
    logits = network(features, batch)
    loss = loss_fn(logits, target)
    loss.backward()
    optimizer.step()
    predicted = logits.detach().argmax(dim=1).cpu().numpy()
    return float(loss.detach()), predicted, target_np


@contextlib.contextmanager
def _tile_scan(
    scan: LabelledScan, config: RandlaConfig, workdir: str | Path | None
) -> Iterator[_Scan]:
    """The scan in a temporary tile store, with its points per tile and label value."""
    chunks = scan.iter_points(chunk_size=config.prediction.chunk_size)
    first = next((c for c in chunks if c.n_points), None)
    if first is None:
        raise TrainingDataError(f"{scan.points_path}: expected points to train on, found none")
    grid = scan_grid(np.asarray(first.xyz[0]), _training_grid_config(config))
    seen = {"intensity": False, "rgb": False}

    def noting(chunk: PointCloud) -> PointCloud:
        seen["intensity"] = seen["intensity"] or bool(np.any(chunk.intensity))
        seen["rgb"] = seen["rgb"] or bool(np.any(chunk.rgb))
        return chunk

    temporary = TemporaryTileStore(
        (noting(c) for c in chain([first], chunks)), grid=grid, workdir=workdir
    )
    try:
        store = temporary.store
        if not store.has_labels:
            raise TrainingDataError(f"{scan.points_path}: training needs labels, found none")
        for wanted, name in ((config.inputs.rgb, "rgb"), (config.inputs.intensity, "intensity")):
            if wanted and not seen[name]:
                raise TrainingDataError(
                    f"{scan.points_path}: [inputs] {name} = true, but every point's {name} is 0: "
                    f"expected a scan with {name}, or {name} = false"
                )
        counts = np.zeros((len(store.tiles), N_CLASSES + 1), np.int64)
        for row, tile in enumerate(store.tiles):
            labels = np.asarray(store.read_core(tile).cloud.labels)
            if labels.size and int(labels.max()) > N_CLASSES:
                raise TrainingDataError(
                    f"{scan.labels_path or scan.points_path}: expected label values "
                    f"0..{N_CLASSES}, found {int(labels.max())}"
                )
            counts[row] = np.bincount(labels, minlength=N_CLASSES + 1)
        yield _Scan(scan.name, store, counts)
    finally:
        temporary.close()


def _training_grid_config(config: RandlaConfig) -> RandlaConfig:
    """The configuration whose tiles are the training stores' (``training.tile_size_m``)."""
    blocks = dataclasses.replace(config.blocks, tile_size_m=config.training.tile_size_m)
    return dataclasses.replace(config, blocks=blocks)


def _round_clouds(
    scans: list[_Scan],
    classes: list[int],
    config: RandlaConfig,
    round_index: int,
    n_batches: int,
    device: Any,
) -> list[SubCloud]:
    """The sub-clouds of one round, in batch order."""
    training = config.training
    blocks = config.blocks
    rng = np.random.default_rng((training.seed, round_index))
    n_clouds = n_batches * training.batch_size
    where = [(s, row) for s, scan in enumerate(scans) for row in range(len(scan.store.tiles))]
    per_tile = np.concatenate([scan.counts for scan in scans])  # (n_all_tiles, 9)
    if training.centres == "balanced":
        slot_values = rng.choice(np.asarray(classes), size=n_clouds)
    else:
        slot_values = np.zeros(n_clouds, np.int64)  # 0 here: any trained class
    tile_of = np.empty(n_clouds, np.int64)
    ordinal = np.empty(n_clouds, np.int64)
    for value in np.unique(slot_values).tolist():
        slots = np.flatnonzero(slot_values == value)
        weights = per_tile[:, classes].sum(axis=1) if value == 0 else per_tile[:, value]
        cumulative = np.cumsum(weights)
        picks = rng.integers(0, int(cumulative[-1]), slots.size)
        tile_of[slots] = np.searchsorted(cumulative, picks, side="right")
        ordinal[slots] = picks - (cumulative[tile_of[slots]] - weights[tile_of[slots]])
    # augmentation and order of each sub-cloud, drawn in slot order
    seeds = rng.integers(0, 2**63 - 1, n_clouds)
    clouds: list[SubCloud | None] = [None] * n_clouds
    half_width = blocks.window_m
    for flat_tile in np.unique(tile_of).tolist():
        scan_number, row = where[flat_tile]
        scan = scans[scan_number]
        tile: TileKey = scan.store.tiles[row]
        core_cloud = scan.store.read_core(tile).cloud  # views of the store: not copied
        core_labels = np.asarray(core_cloud.labels)
        voxels = read_tile_voxels(  # in strips: memory follows the voxels of a dense tile
            scan.store,
            tile,
            halo_m=half_width,
            origin=grid_anchor(scan.store.grid),
            voxel_size_m=blocks.voxel_size_m,
            inputs=config.inputs,
            labels=True,
        ).voxels
        voxel_labels = (
            np.zeros(voxels.n_voxels, np.uint8) if voxels.labels is None else voxels.labels
        )
        target_of = np.full(N_CLASSES + 1, -1, np.int64)
        target_of[classes] = np.arange(len(classes))
        for slot in np.flatnonzero(tile_of == flat_tile).tolist():
            value = int(slot_values[slot])
            eligible = np.isin(core_labels, classes) if value == 0 else core_labels == value
            centre = np.asarray(core_cloud.xyz[np.flatnonzero(eligible)[ordinal[slot]]])
            ids = window(
                voxels.xyz,
                centre_xy=centre[:2],
                half_width_m=half_width,
                max_points=blocks.max_points,
            )
            clouds[slot] = _sub_cloud(
                voxels.xyz[ids],
                voxels.inputs[ids],
                target_of[voxel_labels[ids]],
                centre[:2],
                config,
                np.random.default_rng(int(seeds[slot])),
                device,
            )
    return [c for c in clouds if c is not None]


def _sub_cloud(
    xyz: NDArray[np.float64],
    inputs: NDArray[np.float32],
    targets: NDArray[np.int64],
    centre_xy: NDArray[np.float64],
    config: RandlaConfig,
    rng: np.random.Generator,
    device: Any,
) -> SubCloud:
    """A window's voxels as a training sub-cloud: random order, augmented, with its levels."""
    training = config.training
    order = rng.permutation(xyz.shape[0])
    local = local_coordinates(xyz[order], centre_xy).astype(np.float64)
    if training.rotate:
        angle = rng.uniform(0.0, 2.0 * math.pi)
        cos, sin = math.cos(angle), math.sin(angle)
        local[:, :2] = local[:, :2] @ np.array([[cos, sin], [-sin, cos]])
    if training.flip and rng.random() < 0.5:
        local[:, 0] = -local[:, 0]
    local *= rng.uniform(training.scale_min, training.scale_max, 3)
    if training.jitter_m:
        local += rng.normal(0.0, training.jitter_m, local.shape)
    local32 = np.ascontiguousarray(local, np.float32)
    features = np.concatenate([local32, inputs[order]], axis=1)
    network = config.network
    levels = build_levels(local32, k=network.k_neighbours, ratios=network.ratios, device=device)
    return SubCloud(local32, features, targets[order], levels)


def _save_checkpoint(
    path: Path,
    network: Any,
    optimizer: Any,
    done: int,
    config: RandlaConfig,
    scans: tuple[str, ...],
) -> None:
    """Everything needed to continue: weights, optimizer, torch's generator, batches done."""
    state = {
        "format": _CHECKPOINT_FORMAT,
        "batch": done,
        "config": config_to_dict(config),
        "scans": list(scans),
        "network": network.state_dict(),
        "optimizer": optimizer.state_dict(),
        "torch_rng": torch.get_rng_state(),
    }
    save_checkpoint(path, state)
    logger.info("checkpoint after %d batches: %s", done, path)


def _load_checkpoint(
    path: Path, network: Any, optimizer: Any, config: RandlaConfig, scans: tuple[str, ...]
) -> int:
    state = load_checkpoint(path, version=_CHECKPOINT_FORMAT)
    mine = config_to_dict(config)
    theirs = dict(state["config"])
    # The length of the run (and how predictions are made) may change on resume.
    for table in (mine, theirs):
        table["training"] = {k: v for k, v in table["training"].items() if k != "n_batches"}
        table.pop("prediction", None)
    if theirs != mine:
        raise CheckpointError(
            f"{path}: written with another configuration: expected the one of this run"
        )
    if tuple(state["scans"]) != scans:
        raise CheckpointError(
            f"{path}: written for scans {state['scans']}, found {list(scans)}: expected the same"
        )
    network.load_state_dict(state["network"])
    optimizer.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["torch_rng"])
    return int(state["batch"])
