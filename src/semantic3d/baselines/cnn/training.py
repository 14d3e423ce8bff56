"""Training DeepNet on the paper's schedule: class-balanced batches of 100 points, a random
rotation about z every 100 batches; the cubes are generated on the fly (ours: the paper
does not say how it fed the network).

Each labelled scan is spilled once into a temporary tile store. Training runs in *rounds*
of ``rotate_every`` mini-batches, each with its own draw of points and rotation about z
(:mod:`.rounds`); a producer thread
(:class:`~semantic3d.baselines.common.pipeline.Prefetched`) makes round ``r + 1``'s cubes
(tiles side by side on every core, or the GPU's kernels) while round ``r``
trains, so after the first round the network rarely waits for its input.
Adadelta and the cross-entropy loss; on a CUDA device under bfloat16 autocast
(``[training] autocast``) with deterministic cuDNN algorithms. The loss and the confusion
of the round are summed on the device and read every ``report_every`` batches (every
batch on a CPU, where reading costs nothing), the only waits for the device.

Everything random comes from the seed: round ``r`` draws from ``numpy.random.default_rng
((seed, r))`` and the weights and dropout from torch's generators, whose states are saved
in every checkpoint. The same seed on the same device gives the same model, however the
producer runs ahead, and a run resumed from a checkpoint gives the model of the run that
was not interrupted (tested). ``stop`` (an event: the CLI sets it on Ctrl-C) ends the run
after the current batch with a checkpoint and :class:`TrainingInterrupted`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.baselines.cnn.config import CnnConfig, config_to_dict
from semantic3d.baselines.cnn.model import CnnModel, resolve_device
from semantic3d.baselines.cnn.network import build_network
from semantic3d.baselines.cnn.point_cubes_torch import unpack_cubes
from semantic3d.baselines.cnn.rounds import Round, RoundProgress, TiledScan, make_round
from semantic3d.baselines.common.pipeline import Prefetched
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.core.classes import N_CLASSES, class_by_value
from semantic3d.core.errors import Semantic3DError, require
from semantic3d.core.threads import thread_budget
from semantic3d.spatial.grid import TileGrid
from semantic3d.spatial.store import TemporaryTileStore

torch: Any = require("torch", "torch")

__all__ = ["CheckpointError", "TrainingInterrupted", "TrainingProgress", "train_cnn_model"]

logger = logging.getLogger(__name__)

_CHECKPOINT_FORMAT = 1
_REPORT_EVERY = {"cpu": 1, "cuda": 25}
"""Batches between two reads of the loss (each read waits for the device)."""
_WAIT_POLL_S = 0.25


class CheckpointError(Semantic3DError, ValueError):
    """A checkpoint cannot resume this run (another configuration, other scans, corrupt)."""


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped on request (``stop``, Ctrl-C at the CLI) after ``batch`` batches;
    ``checkpoint`` (when given) holds them, and ``resume`` continues from it."""

    def __init__(self, batch: int, checkpoint: Path | None) -> None:
        where = f"; checkpoint {checkpoint}" if checkpoint is not None else ""
        super().__init__(f"training stopped after {batch} batches{where}")
        self.batch = batch
        self.checkpoint = checkpoint


@dataclass(frozen=True, slots=True)
class TrainingProgress:
    """Where a training run stands.

    Attributes:
        batch: mini-batches done.
        n_batches: mini-batches of the run.
        loss: mean cross-entropy of the current round's batches so far.
        balanced_accuracy: mean per-class recall on the current round's batches so far.
        stage: ``"cubes"`` while training waits for a round's cubes, else ``"train"``.
        cube_points: while waiting, points of that round whose cubes are done.
        cube_points_total: while waiting, points of that round.
    """

    batch: int
    n_batches: int
    loss: float
    balanced_accuracy: float
    stage: str = "train"
    cube_points: int = 0
    cube_points_total: int = 0


Progress = Callable[[TrainingProgress], None]


def train_cnn_model(
    scans: Sequence[LabelledScan],
    *,
    config: CnnConfig,
    device: str = "cpu",
    checkpoint: str | Path | None = None,
    resume: bool = False,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    stop: threading.Event | None = None,
    report_every: int | None = None,
) -> CnnModel:
    """Train DeepNet on labelled scans with ``config.training``'s schedule.

    Args:
        scans: the labelled scans.
        config: the configuration (``training.n_batches`` sets the length of the run).
        device: ``cpu`` or ``cuda``.
        checkpoint: file to write every ``training.checkpoint_every`` batches and when
            stopped (and to resume from).
        resume: continue from ``checkpoint`` (which must exist and match this run).
        workdir: scratch folder for the scans' tile stores (removed afterwards).
        progress: called every ``report_every`` batches, at the end of each round, and
            while training waits for a round's cubes.
        stop: when set, the run ends after the current batch: a checkpoint is written and
            :class:`TrainingInterrupted` raised.
        report_every: batches between two progress reports (default: 1 on a CPU, 25 on
            a GPU, where each report waits for the device).

    Raises:
        TrainingDataError: no scan, fewer than two classes, a listed class without points.
        CheckpointError: ``resume`` without a usable checkpoint.
        TrainingInterrupted: ``stop`` was set.
    """
    started = time.perf_counter()
    if not scans:
        raise TrainingDataError("training needs at least one labelled scan")
    if resume and (checkpoint is None or not Path(checkpoint).is_file()):
        raise CheckpointError(f"{checkpoint}: expected a checkpoint to resume from, found none")
    torch_device = resolve_device(device)
    cuda = torch_device.type == "cuda"
    training = config.training
    torch.manual_seed(training.seed)
    network = build_network(config.cubes, config.network)
    network.to(torch_device, memory_format=torch.channels_last_3d)  # see CnnModel
    optimizer = torch.optim.Adadelta(
        network.parameters(), lr=training.learning_rate, rho=training.rho
    )
    names = tuple(s.name for s in scans)
    path = None if checkpoint is None else Path(checkpoint)
    done = 0
    if resume and path is not None:  # checked above: resume needs the file
        done = _load_checkpoint(path, network, optimizer, config=config, scans=names)
    every = report_every or _REPORT_EVERY["cuda" if cuda else "cpu"]
    with contextlib.ExitStack() as stack:
        tiled = [stack.enter_context(_tile_scan(scan, config, workdir)) for scan in scans]
        totals = sum(s.counts.sum(axis=0) for s in tiled)
        classes = _training_classes(totals, config, names)
        stack.enter_context(_deterministic(cuda))
        cancel = threading.Event()
        made = RoundProgress()
        n_rounds = -(-training.n_batches // training.rotate_every)
        start = done // training.rotate_every

        def produce() -> Iterator[Round]:
            for index in range(start, n_rounds):
                length = min(
                    training.rotate_every, training.n_batches - index * training.rotate_every
                )
                yield make_round(
                    tiled,
                    classes,
                    config,
                    index,
                    length,
                    device=torch_device,
                    n_threads=thread_budget(),
                    progress=made,
                    cancel=cancel,
                )

        rounds = stack.enter_context(
            Prefetched(produce, depth=1, device=torch_device, name="training-rounds")
        )
        stack.callback(cancel.set)  # first on the way out: the producer stops between tiles
        state = _Loop(network, optimizer, config, torch_device, every, progress)
        network.train()
        while done < training.n_batches:
            first = (done // training.rotate_every) * training.rotate_every
            current = _next_round(rounds, made, done, training.n_batches, progress, stop)
            if current is None:  # stopped while waiting: the state is that of `done`
                _stopped(path, network, optimizer, done, config, names)
            done = state.run_round(current, first, done, stop, path, names)
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


def _next_round(
    rounds: Prefetched[Round],
    made: RoundProgress,
    done: int,
    n_batches: int,
    progress: Progress | None,
    stop: threading.Event | None,
) -> Round | None:
    """The next round's cubes, reporting the producer's progress while waiting for them;
    ``None`` when ``stop`` is set meanwhile."""
    while True:
        if stop is not None and stop.is_set():
            return None
        arrived, current = rounds.poll(_WAIT_POLL_S)
        if arrived:
            return current
        if progress is not None:
            progress(
                TrainingProgress(
                    done, n_batches, math.nan, math.nan, "cubes", made.points, made.total
                )
            )


class _Loop:
    """The optimisation steps of a run, with the round's loss and confusion kept on the
    device."""

    def __init__(
        self,
        network: Any,
        optimizer: Any,
        config: CnnConfig,
        device: Any,
        report_every: int,
        progress: Progress | None,
    ) -> None:
        self.network = network
        self.optimizer = optimizer
        self.config = config
        self.device = device
        self.report_every = report_every
        self.progress = progress
        self.loss_fn = torch.nn.CrossEntropyLoss()
        size = config.cubes.cube_voxels
        self.shape = (config.cubes.n_scales, size, size, size)
        cuda = device.type == "cuda"
        self.autocast = cuda and config.training.autocast and bool(torch.cuda.is_bf16_supported())

    def run_round(
        self,
        current: Round,
        first: int,
        done: int,
        stop: threading.Event | None,
        checkpoint: Path | None,
        names: tuple[str, ...],
    ) -> int:
        """Train the batches of ``current`` from batch ``done``; returns batches done."""
        training = self.config.training
        batch_size = training.batch_size
        n_round = current.targets.shape[0] // batch_size
        loss_sum = torch.zeros((), dtype=torch.float64, device=self.device)
        confusion = torch.zeros(N_CLASSES * N_CLASSES, dtype=torch.int64, device=self.device)
        begin = done - first
        for batch in range(begin, n_round):
            if stop is not None and stop.is_set():
                _stopped(checkpoint, self.network, self.optimizer, done, self.config, names)
            rows = slice(batch * batch_size, (batch + 1) * batch_size)
            cubes = unpack_cubes(current.packed[rows], self.shape, dtype=torch.float32)
            target = current.targets[rows]
            logits, loss = self._step(cubes, target)
            loss_sum += loss.detach()
            confusion += torch.bincount(
                target * N_CLASSES + logits.detach().argmax(dim=1), minlength=N_CLASSES**2
            )
            done += 1
            if self.progress is not None and (
                done % self.report_every == 0 or batch == n_round - 1
            ):
                self.progress(
                    TrainingProgress(
                        done,
                        training.n_batches,
                        float(loss_sum) / (batch + 1 - begin),
                        _balanced_accuracy(confusion.view(N_CLASSES, N_CLASSES).cpu().numpy()),
                    )
                )
            if (
                checkpoint is not None
                and training.checkpoint_every
                and done % training.checkpoint_every == 0
                and done < training.n_batches
            ):
                _save_checkpoint(checkpoint, self.network, self.optimizer, done, self.config, names)
        return done

    def _step(self, cubes: Any, target: Any) -> tuple[Any, Any]:
        self.optimizer.zero_grad(set_to_none=True)
        mixed = (
            torch.autocast("cuda", dtype=torch.bfloat16)
            if self.autocast
            else contextlib.nullcontext()
        )
        with mixed:
            logits = self.network(cubes)
            loss = self.loss_fn(logits.float(), target)
        loss.backward()
        self.optimizer.step()
        return logits, loss


@contextlib.contextmanager
def _deterministic(cuda: bool) -> Iterator[None]:
    """Deterministic cuDNN algorithms while training on a GPU (same seed, same model)."""
    if not cuda:
        yield
        return
    before = torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    try:
        yield
    finally:
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = before


def _stopped(
    checkpoint: Path | None,
    network: Any,
    optimizer: Any,
    done: int,
    config: CnnConfig,
    names: tuple[str, ...],
) -> NoReturn:
    if checkpoint is not None:
        _save_checkpoint(checkpoint, network, optimizer, done, config, names)
    raise TrainingInterrupted(done, checkpoint)


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
        yield TiledScan(scan.name, store, store.tiles, counts)
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
    if torch.cuda.is_available() and any(p.is_cuda for p in network.parameters()):
        state["cuda_rng"] = torch.cuda.get_rng_state()
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
    # The length of the run may change on resume, and prediction settings do not touch
    # training; nothing else may change.
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
    if "cuda_rng" in state and any(p.is_cuda for p in network.parameters()):
        torch.cuda.set_rng_state(state["cuda_rng"])
    return int(state["batch"])
