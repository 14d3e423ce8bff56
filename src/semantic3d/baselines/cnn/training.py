"""Training DeepNet on the paper's schedule: class-balanced batches of 100 points, a random
rotation about z every 100 batches; the cubes are generated on the fly (ours: the paper
does not say how it fed the network).

Each labelled scan is spilled once into a temporary tile store. Training runs in *rounds*
of ``rotate_every`` mini-batches: a round draws its ``rotate_every x batch_size`` points
(every batch class-balanced: the classes take turns over its slots, and each slot is a
point of its class drawn uniformly over all scans), draws one rotation about z, reads
each tile holding drawn points with its halo, rotates it about the tile's centre and fills
the drawn points' cubes (kept bit-packed, 2.5 kB a point). Its batches then go through
Adadelta and the cross-entropy loss. The scans' cubes are never all held.

Everything random comes from the seed: round ``r`` draws from ``numpy.random.default_rng
((seed, r))`` and the weights and dropout from torch's generator, whose state is saved in
every checkpoint. The same seed on the same device gives the same model, and a run
resumed from a checkpoint gives the model of the run that was not interrupted (tested).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.baselines.cnn.config import CnnConfig, config_to_dict
from semantic3d.baselines.cnn.cubes import build_occupancy, compute_cubes
from semantic3d.baselines.cnn.model import CnnModel, resolve_device
from semantic3d.baselines.cnn.network import build_network
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.core.classes import N_CLASSES, class_by_value
from semantic3d.core.errors import Semantic3DError, require
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TemporaryTileStore, TileStore

torch: Any = require("torch", "torch")

__all__ = ["CheckpointError", "TrainingProgress", "train_cnn_model"]

logger = logging.getLogger(__name__)

_CHECKPOINT_FORMAT = 1


class CheckpointError(Semantic3DError, ValueError):
    """A checkpoint cannot resume this run (another configuration, other scans, corrupt)."""


@dataclass(frozen=True, slots=True)
class TrainingProgress:
    """Where a training run stands, after each mini-batch.

    Attributes:
        batch: mini-batches done.
        n_batches: mini-batches of the run.
        loss: mean cross-entropy of the current round's batches so far.
        balanced_accuracy: mean per-class recall on the current round's batches so far.
        stage: ``"cubes"`` while a round's cubes are generated, else ``"train"``.
    """

    batch: int
    n_batches: int
    loss: float
    balanced_accuracy: float
    stage: str = "train"


Progress = Callable[[TrainingProgress], None]


@dataclass(slots=True)
class _Scan:
    name: str
    store: TileStore
    tiles: tuple[TileKey, ...]
    counts: NDArray[np.int64]  # (n_tiles, N_CLASSES + 1) points per tile and label value


def train_cnn_model(
    scans: Sequence[LabelledScan],
    *,
    config: CnnConfig,
    device: str = "cpu",
    checkpoint: str | Path | None = None,
    resume: bool = False,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
) -> CnnModel:
    """Train DeepNet on labelled scans with ``config.training``'s schedule.

    Args:
        scans: the labelled scans.
        config: the configuration (``training.n_batches`` sets the length of the run).
        device: ``cpu`` or ``cuda``.
        checkpoint: file to write every ``training.checkpoint_every`` batches (and to
            resume from).
        resume: continue from ``checkpoint`` (which must exist and match this run).
        workdir: scratch folder for the scans' tile stores (removed afterwards).
        progress: called after every batch.

    Raises:
        TrainingDataError: no scan, fewer than two classes, a listed class without points.
        CheckpointError: ``resume`` without a usable checkpoint.
    """
    started = time.perf_counter()
    if not scans:
        raise TrainingDataError("training needs at least one labelled scan")
    if resume and (checkpoint is None or not Path(checkpoint).is_file()):
        raise CheckpointError(f"{checkpoint}: expected a checkpoint to resume from, found none")
    torch_device = resolve_device(device)
    training = config.training
    torch.manual_seed(training.seed)
    network = build_network(config.cubes, config.network)
    network.to(torch_device, memory_format=torch.channels_last_3d)  # see CnnModel
    optimizer = torch.optim.Adadelta(
        network.parameters(), lr=training.learning_rate, rho=training.rho
    )
    names = tuple(s.name for s in scans)
    done = 0
    if resume and checkpoint is not None:  # checked above: resume needs the file
        done = _load_checkpoint(Path(checkpoint), network, optimizer, config=config, scans=names)
    loss_fn = torch.nn.CrossEntropyLoss()
    with contextlib.ExitStack() as stack:
        tiled = [stack.enter_context(_tile_scan(scan, config, workdir)) for scan in scans]
        totals = sum(s.counts.sum(axis=0) for s in tiled)
        classes = _training_classes(totals, config, names)
        size = config.cubes.cube_voxels
        shape = (config.cubes.n_scales, size, size, size)
        network.train()
        while done < training.n_batches:
            round_index = done // training.rotate_every
            first = round_index * training.rotate_every
            n_round = min(training.rotate_every, training.n_batches - first)
            if progress is not None:
                progress(TrainingProgress(done, training.n_batches, math.nan, math.nan, "cubes"))
            packed, labels = _round_cubes(tiled, classes, config, round_index, n_round)
            confusion = np.zeros((N_CLASSES, N_CLASSES), np.int64)
            losses: list[float] = []
            for batch in range(done - first, n_round):
                rows = slice(batch * training.batch_size, (batch + 1) * training.batch_size)
                bits = np.unpackbits(packed[rows], axis=1, count=math.prod(shape))
                cubes = torch.from_numpy(bits.reshape(-1, *shape).astype(np.float32))
                target = torch.from_numpy(labels[rows].astype(np.int64) - 1)
                cubes, target = cubes.to(torch_device), target.to(torch_device)
                optimizer.zero_grad(set_to_none=True)
                logits = network(cubes)
                loss = loss_fn(logits, target)
                loss.backward()
                optimizer.step()
                losses.append(float(loss.detach()))
                predicted = logits.detach().argmax(dim=1).cpu().numpy()
                np.add.at(confusion, (target.cpu().numpy(), predicted), 1)
                done += 1
                if progress is not None:
                    progress(
                        TrainingProgress(
                            done,
                            training.n_batches,
                            float(np.mean(losses)),
                            _balanced_accuracy(confusion),
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
    return CnnModel(
        network,
        config=config,
        label_values=tuple(classes),
        training_scans=names,
        seed=training.seed,
        n_batches_trained=done,
        training_time_s=time.perf_counter() - started,
        package_version=__version__,
    )


@contextlib.contextmanager
def _tile_scan(scan: LabelledScan, config: CnnConfig, workdir: str | Path | None) -> Any:
    """The scan in a temporary tile store, with its points per tile and label value."""
    training = config.training
    grid = TileGrid.square(training.tile_size_m)
    chunks = scan.iter_points(chunk_size=config.prediction.chunk_size)
    temporary = TemporaryTileStore(chunks, grid=grid, workdir=workdir)
    try:
        store = temporary.store
        if not store.has_labels:
            raise TrainingDataError(f"{scan.points_path}: training needs labels, found none")
        counts = np.zeros((len(store.tiles), N_CLASSES + 1), np.int64)
        for row, tile in enumerate(store.tiles):
            labels = np.asarray(store.read_core(tile).cloud.labels)
            if labels.size and int(labels.max()) > N_CLASSES:
                raise TrainingDataError(
                    f"{scan.labels_path or scan.points_path}: expected label values "
                    f"0..{N_CLASSES}, found {int(labels.max())}"
                )
            counts[row] = np.bincount(labels, minlength=N_CLASSES + 1)
        yield _Scan(scan.name, store, store.tiles, counts)
    finally:
        temporary.close()


def _training_classes(
    totals: NDArray[np.int64], config: CnnConfig, names: tuple[str, ...]
) -> list[int]:
    present = [v for v in range(1, N_CLASSES + 1) if totals[v] > 0]
    classes = list(config.training.classes) or present
    missing = [v for v in classes if totals[v] == 0]
    if missing:
        listed = ", ".join(f"{v} ({class_by_value(v).name})" for v in missing)
        raise TrainingDataError(
            f"class(es) {listed} have no labelled point in the training scans {list(names)}: "
            "remove them from [training] classes or add scans"
        )
    if len(classes) < 2:
        raise TrainingDataError(
            f"training needs at least 2 labelled classes, found {classes or 'none'} in "
            f"{list(names)}"
        )
    return sorted(classes)


def _round_cubes(
    scans: list[_Scan], classes: list[int], config: CnnConfig, round_index: int, n_batches: int
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Bit-packed cubes and label values of one round's points, in batch order."""
    training = config.training
    cubes = config.cubes
    rng = np.random.default_rng((training.seed, round_index))
    n_points = n_batches * training.batch_size
    slot_classes = np.concatenate(
        [
            rng.permutation(np.resize(np.asarray(classes), training.batch_size))
            for _ in range(n_batches)
        ]
    )
    angle = float(rng.uniform(0.0, 2.0 * math.pi))
    # Each slot: a uniformly drawn point of its class over every tile of every scan.
    where = [(s, row) for s, scan in enumerate(scans) for row in range(len(scan.tiles))]
    per_tile = np.concatenate([scan.counts for scan in scans])  # (n_all_tiles, 9)
    tile_of = np.empty(n_points, np.int64)
    ordinal = np.empty(n_points, np.int64)
    for value in classes:
        slots = np.flatnonzero(slot_classes == value)
        cumulative = np.cumsum(per_tile[:, value])
        picks = rng.integers(0, int(cumulative[-1]), slots.size)
        tile_of[slots] = np.searchsorted(cumulative, picks, side="right")
        ordinal[slots] = picks - (cumulative[tile_of[slots]] - per_tile[tile_of[slots], value])
    size = cubes.cube_voxels
    n_bytes = (cubes.n_scales * size**3 + 7) // 8
    packed = np.zeros((n_points, n_bytes), np.uint8)
    halo = cubes.reach_m * math.sqrt(2.0)  # the rotated tile needs its reach in any direction
    cos, sin = math.cos(angle), math.sin(angle)
    for flat_tile in np.unique(tile_of).tolist():
        scan_number, row = where[flat_tile]
        scan = scans[scan_number]
        tile = scan.tiles[row]
        slots = np.flatnonzero(tile_of == flat_tile)
        data = scan.store.read(tile, halo_m=halo)
        core_labels = np.asarray(data.core.cloud.labels)
        chosen = np.empty(slots.size, np.int64)
        for value in np.unique(slot_classes[slots]).tolist():
            of_class = slots[slot_classes[slots] == value]
            chosen[np.searchsorted(slots, of_class)] = np.flatnonzero(core_labels == value)[
                ordinal[of_class]
            ]
        x0, y0, x1, y1 = data.bounds
        centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
        xyz = np.concatenate([np.asarray(data.core.cloud.xyz), np.asarray(data.halo.cloud.xyz)])
        local = xyz - centre
        rotated = np.column_stack(
            [
                cos * local[:, 0] - sin * local[:, 1],
                sin * local[:, 0] + cos * local[:, 1],
                local[:, 2],
            ]
        )
        origin = np.zeros(3)
        occupancy = build_occupancy(
            rotated, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring=cubes.centring
        )
        filled = compute_cubes(
            occupancy, rotated[chosen], cube_voxels=size, centring=cubes.centring
        )
        packed[slots] = np.packbits(filled.reshape(slots.size, -1).astype(np.uint8), axis=1)
    return packed, slot_classes.astype(np.uint8)


def _balanced_accuracy(confusion: NDArray[np.int64]) -> float:
    totals = confusion.sum(axis=1)
    seen = totals > 0
    if not seen.any():
        return math.nan
    return float(np.mean(np.diag(confusion)[seen] / totals[seen]))


def _save_checkpoint(
    path: Path,
    network: Any,
    optimizer: Any,
    done: int,
    config: CnnConfig,
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
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.partial")
    try:
        torch.save(state, temp)
        temp.replace(path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
    logger.info("checkpoint after %d batches: %s", done, path)


def _load_checkpoint(
    path: Path,
    network: Any,
    optimizer: Any,
    *,
    config: CnnConfig,
    scans: tuple[str, ...],
) -> int:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds on a file that is not its own
        raise CheckpointError(f"{path}: not a training checkpoint: {exc}") from exc
    if not isinstance(state, dict) or state.get("format") != _CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: expected checkpoint format {_CHECKPOINT_FORMAT}")
    mine = config_to_dict(config)
    theirs = dict(state["config"])
    # The length of the run may change on resume; nothing else may.
    for table in (mine, theirs):
        table["training"] = {k: v for k, v in table["training"].items() if k != "n_batches"}
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
