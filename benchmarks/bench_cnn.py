"""Throughput of the CNN baseline (DeepNet): cubes, network, predict, training, each with
its floor. ``python benchmarks/bench_cnn.py [--device cpu|cuda] [--quick] [--only ...]``.

Sections (``--only floors,cubes,network,predict,train``; default all), on real scans (CMU
Oakland, ../shared/data/oakland, 2-9 cm point spacing) and a dense synthetic worst case,
with the paper's cubes (5 scales of 16^3 voxels, 2.5-40 cm) and network (5.6 M
parameters, untrained: speed does not depend on the weights):

- floors: the device's measured matrix rate (float32 on a CPU, float16 on a GPU) and
  copy bandwidth; every section divides its work by them: FLOPs per point over the
  matrix rate, bytes per point over the bandwidth.
- cubes: point-centred cubes by the torch kernel on the device
  (:mod:`semantic3d.baselines.cnn.point_cubes_torch`) against the compiled CPU kernel
  (numba, all host cores) and the straightforward exact version (scipy cKDTree
  neighbours placed by the formula), identical cubes (checked); corner-centred cubes by
  the compiled kernel against numpy and cKDTree. Floor: the cube's bytes written once.
- network: DeepNet alone, eager float32 in the default layout (the reference),
  channels-last, bfloat16 autocast, float16 (GPU) and the labelling form as predict runs
  it, compiled (``torch.compile``; ~50 s to compile on a busy 2-core CPU). Floors: 134
  MFLOP a point, and the activations' bytes (each layer's output written and read once).
- predict: ``predict_scans`` end to end on a folder (read ASCII, tile store, cubes,
  network, ``.labels`` + run record) in a fresh process: points/s, CPU seconds, peak RSS.
  CPU: 6 m crops of two scans; GPU: the 10 scans whole.
- train: the training loop (rounds of cubes made by a producer thread while the previous
  round trains) on Oakland scans: batches/s, the time of the paper's 74,700 batches at
  that rate, the time one round's cubes take alone, and the floor (3x the forward FLOPs
  a batch).

On a CPU, rates are also given per CPU second (``time.process_time``, all threads), so
that gains show on a shared machine; the load average is recorded. Writes
``benchmarks/out/bench_cnn.json`` (``bench_cnn_cuda.json`` for ``--device cuda``).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import peak_rss_mb

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
DATA = Path(os.environ.get("BENCH_CNN_DATA", ROOT.parent / "shared" / "data" / "oakland"))
SCAN = "oakland_part2_ac"
PAPER_BATCHES = 74_700


def set_data(folder: Path) -> None:
    """Read the Oakland samples from ``folder`` (children get it through the environment)."""
    global DATA
    DATA = Path(folder).resolve()  # predict links scans into a scratch folder
    os.environ["BENCH_CNN_DATA"] = str(DATA)


def _load_xyz(scan: str = SCAN) -> np.ndarray:
    from semantic3d.io.formats import read_points

    return np.asarray(read_points(DATA / f"{scan}.txt").xyz)


def _sync(device: str) -> None:
    if device == "cuda":
        import torch

        torch.cuda.synchronize()


def _timed(run: Callable[[], Any], device: str = "cpu") -> tuple[Any, float, float]:
    """``(value, wall_s, cpu_s)`` of ``run()`` (CPU seconds of every thread)."""
    _sync(device)
    cpu, wall = time.process_time(), time.perf_counter()
    value = run()
    _sync(device)
    return value, time.perf_counter() - wall, time.process_time() - cpu


def _rate(points: int, wall_s: float, cpu_s: float) -> dict[str, float]:
    return {
        "points": points,
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "points_per_s": points / wall_s,
        "points_per_cpu_s": points / cpu_s if cpu_s > 0 else float("nan"),
    }


# -- floors ---------------------------------------------------------------------------------
def bench_floors(device: str, quick: bool) -> dict[str, Any]:
    """The device's matrix rate and copy bandwidth, measured."""
    import torch

    dtype = torch.float16 if device == "cuda" else torch.float32
    size = 8192 if device == "cuda" else (1024 if quick else 2048)
    a = torch.randn(size, size, device=device, dtype=dtype)
    b = torch.randn(size, size, device=device, dtype=dtype)
    a @ b
    best = min(_timed(lambda: a @ b, device)[1] for _ in range(3))
    elements = (1 << 28 if device == "cuda" else 1 << 25) // 4
    source = torch.ones(elements, device=device)
    target = torch.empty_like(source)
    target.copy_(source)
    copy = min(_timed(lambda: target.copy_(source), device)[1] for _ in range(3))
    return {
        "matmul_dtype": str(dtype).removeprefix("torch."),
        "matmul_flops_per_s": 2 * size**3 / best,
        "copy_bytes_per_s": 2 * 4 * elements / copy,  # read + write
        "threads": torch.get_num_threads(),
    }


def network_flops(channels: tuple[int, ...] = (16, 32, 64), size: int = 16) -> int:
    """Multiply-adds x 2 of one point's forward pass (convolutions + linear layers)."""
    macs, previous, side = 0, 1, size
    for width in channels:
        macs += side**3 * width * previous * 27
        previous, side = width, side // 2
    macs *= 5
    macs += 2560 * 2048 + 2048 * 8
    return 2 * macs


def activation_bytes(element_bytes: int, channels: tuple[int, ...] = (16, 32, 64)) -> int:
    """Bytes one point's forward pass moves when each layer's output is written once and
    read once (the unfused network: the input, then per convolution its output, the
    ReLU's and the pooled one), over the 5 scales."""
    total, side = 16**3, 16  # the input cube, read once
    for width in channels:
        volume = side**3 * width
        total += 2 * (volume + volume + volume // 8)
        side //= 2
    return 5 * total * element_bytes


def _floors(points: int, floors: dict[str, Any], *, flops: float, moved: float) -> dict[str, Any]:
    """The least time ``points`` need on this device: arithmetic and memory bounds."""
    return {
        "flops_per_point": flops,
        "bytes_per_point": moved,
        "flops_floor_s": points * flops / floors["matmul_flops_per_s"],
        "bytes_floor_s": points * moved / floors["copy_bytes_per_s"],
    }


# -- cubes ----------------------------------------------------------------------------------
def numpy_cubes(keys: tuple[np.ndarray, ...], corners: np.ndarray, size: int) -> np.ndarray:
    """Every cube voxel's key looked up with np.searchsorted (batches of 64 points)."""
    from semantic3d.spatial.voxels import pack_keys

    axis = np.arange(size)
    offsets = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros((corners.shape[0], len(keys), size, size, size), np.float32)
    for begin in range(0, corners.shape[0], 64):
        part = corners[begin : begin + 64]
        for scale, sorted_keys in enumerate(keys):
            cells = (part[:, scale, None, :] + offsets).reshape(-1, 3)
            packed = pack_keys(cells)
            found = np.minimum(np.searchsorted(sorted_keys, packed), sorted_keys.size - 1)
            hit = sorted_keys[found] == packed
            out[begin : begin + 64, scale] = hit.reshape(-1, size, size, size)
    return out


def tree_cubes(
    xyz: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...], size: int
) -> np.ndarray:
    """Each point's neighbours from a k-d tree, marked into its cubes one by one."""
    from scipy.spatial import cKDTree

    from semantic3d.baselines.cnn.cubes import compute_corner_cells

    tree = cKDTree(xyz)
    corners = compute_corner_cells(queries, origin=origin, voxel_sizes_m=sizes, cube_voxels=size)
    out = np.zeros((queries.shape[0], len(sizes), size, size, size), np.float32)
    for scale, voxel in enumerate(sizes):
        cells_all = np.floor((xyz - origin) / voxel).astype(np.int64)
        near = tree.query_ball_point(queries, r=(size / 2 + 1) * voxel, p=np.inf)
        for q, neighbours in enumerate(near):
            cells = cells_all[neighbours] - corners[q, scale]
            inside = np.all((cells >= 0) & (cells < size), axis=1)
            i, j, k = cells[inside].T
            out[q, scale, i, j, k] = 1.0
    return out


def tree_point_cubes(
    xyz: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...], size: int
) -> np.ndarray:
    """Point-centred cubes: each point's neighbours from a k-d tree, placed by the exact
    integer/fraction formula of :mod:`semantic3d.baselines.cnn.point_cubes`."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xyz)
    out = np.zeros((queries.shape[0], len(sizes), size, size, size), np.float32)
    for scale, voxel in enumerate(sizes):
        scaled = (xyz - origin) / voxel
        cells = np.floor(scaled)
        fractions = scaled - cells
        q_scaled = (queries - origin) / voxel
        q_cells = np.floor(q_scaled)
        q_fractions = q_scaled - q_cells
        near = tree.query_ball_point(queries, r=(size / 2 + 0.5) * voxel, p=np.inf)
        for q, neighbours in enumerate(near):
            index = (cells[neighbours] - q_cells[q]).astype(np.int64) + size // 2
            index -= fractions[neighbours] < q_fractions[q]
            inside = np.all((index >= 0) & (index < size), axis=1)
            i, j, k = index[inside].T
            out[q, scale, i, j, k] = 1.0
    return out


def dense_surfaces(spacing_m: float = 0.01) -> np.ndarray:
    """A dense static scan's worst case: 6 x 6 m of ground and a 3 x 3 m plane tilted
    against all three axes (its own skyline), both sampled every ``spacing_m`` with 2 mm
    noise (450,000 points at 1 cm)."""
    rng = np.random.default_rng(0)
    grid = np.mgrid[0:6:spacing_m, 0:6:spacing_m].reshape(2, -1).T
    ground = np.column_stack([grid, rng.normal(0, 0.002, len(grid))])
    plane = np.mgrid[0:3:spacing_m, 0:3:spacing_m].reshape(2, -1).T
    a = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    b = np.array([1.0, 1.0, -2.0]) / np.sqrt(6)
    normal = np.ones(3) / np.sqrt(3)
    tilted = (
        plane[:, :1] * a + plane[:, 1:] * b + 2.0 + rng.normal(0, 0.002, (len(plane), 1)) * normal
    )
    return np.concatenate([ground, tilted])


def bench_point_cubes(
    xyz: np.ndarray, n_queries: int, device: str, floors: dict[str, Any]
) -> dict[str, Any]:
    """Point-centred cubes: the torch kernel on ``device`` and the compiled CPU kernel
    against the cKDTree reference, and corner-centred ones; same run, same points."""
    import torch

    from semantic3d.baselines.cnn.config import CubeConfig
    from semantic3d.baselines.cnn.cubes import build_occupancy, compute_cubes
    from semantic3d.baselines.cnn.point_cubes_torch import DevicePointCubes
    from semantic3d.spatial.voxels import grid_origin

    cubes = CubeConfig(centring="point")
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=max(cubes.voxel_sizes_m))
    queries = xyz[np.random.default_rng(0).choice(len(xyz), n_queries, replace=False)]
    corner = build_occupancy(xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m)
    compute_cubes(corner, queries[:8], cube_voxels=16, centring="corner")  # compiled
    _, corner_s, corner_cpu = _timed(
        lambda: compute_cubes(corner, queries, cube_voxels=16, centring="corner")
    )
    build_occupancy(xyz[:1000], origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring="point")
    occupancy, occ_s, occ_cpu = _timed(
        lambda: build_occupancy(
            xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring="point"
        )
    )
    assert occupancy.summaries is not None
    compute_cubes(occupancy, queries[:8], cube_voxels=16, centring="point")  # compiled
    ours, ours_s, ours_cpu = _timed(
        lambda: compute_cubes(occupancy, queries, cube_voxels=16, centring="point")
    )
    held, upload_s, _ = _timed(
        lambda: DevicePointCubes(occupancy, device=device, cube_voxels=16), device
    )
    dtype = torch.float16 if device == "cuda" else torch.float32
    cells, fractions = held.anchors(queries)
    held.fill(cells[:8], fractions[:8], dtype=dtype)
    on_device, device_s, device_cpu = _timed(
        lambda: held.fill(cells, fractions, dtype=dtype), device
    )
    assert np.array_equal(on_device.float().cpu().numpy(), ours)
    del on_device
    few = max(n_queries // 10, 1)
    tree, tree_s, tree_cpu = _timed(
        lambda: tree_point_cubes(xyz, queries[:few], origin, cubes.voxel_sizes_m, 16)
    )
    assert np.array_equal(ours[:few], tree)
    cube_bytes = cubes.n_scales * 16**3 * (2 if device == "cuda" else 4)
    return {
        "scan_points": len(xyz),
        "occupancy_build_s": occ_s,
        "occupancy_build_cpu_s": occ_cpu,
        "summary_rows_per_scale": [int(s.fractions.shape[0]) for s in occupancy.summaries],
        "occupied_cells_per_scale": [int(k.size) for k in occupancy.keys],
        "device_upload_s": upload_s,
        "torch_kernel_on_device": _rate(n_queries, device_s, device_cpu),
        "compiled_cpu_kernel": _rate(n_queries, ours_s, ours_cpu),
        "compiled_corner_kernel": _rate(n_queries, corner_s, corner_cpu),
        "ckdtree_point": _rate(few, tree_s, tree_cpu),
        "floor": _floors(n_queries, floors, flops=0, moved=cube_bytes),
        "occupancy": float(ours.mean()),
        "identical": True,
    }


def bench_cubes(n_queries: int) -> dict[str, Any]:
    from semantic3d.baselines.cnn.config import CubeConfig
    from semantic3d.baselines.cnn.cubes import build_occupancy, compute_corner_cells, fill_cubes
    from semantic3d.spatial.voxels import grid_origin

    cubes = CubeConfig()
    xyz = _load_xyz()
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=max(cubes.voxel_sizes_m))
    queries = xyz[np.random.default_rng(0).choice(len(xyz), n_queries, replace=False)]
    occupancy, occ_s, occ_cpu = _timed(
        lambda: build_occupancy(xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m)
    )
    corners = compute_corner_cells(
        queries, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, cube_voxels=16
    )
    fill_cubes(occupancy, corners[:8], cube_voxels=16)  # compiled / loaded from cache
    ours, ours_s, ours_cpu = _timed(lambda: fill_cubes(occupancy, corners, cube_voxels=16))
    plain, plain_s, plain_cpu = _timed(lambda: numpy_cubes(occupancy.keys, corners, 16))
    few = max(n_queries // 10, 1)
    tree, tree_s, tree_cpu = _timed(
        lambda: tree_cubes(xyz, queries[:few], origin, cubes.voxel_sizes_m, 16)
    )
    assert np.array_equal(ours, plain) and np.array_equal(ours[:few], tree)
    return {
        "scan_points": len(xyz),
        "occupancy_build_s": occ_s,
        "occupancy_build_cpu_s": occ_cpu,
        "fill_cubes": {"points": n_queries, "wall_s": ours_s, "cpu_s": ours_cpu},
        "numpy_searchsorted": {"points": n_queries, "wall_s": plain_s, "cpu_s": plain_cpu},
        "ckdtree": {"points": few, "wall_s": tree_s, "cpu_s": tree_cpu},
        "occupancy": float(ours.mean()),
    }


# -- network --------------------------------------------------------------------------------
def bench_network(
    device: str, batch: int, repeat: int, compile_network: bool, floors: dict[str, Any]
) -> dict[str, Any]:
    import torch

    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.cnn.inference import InferenceNetwork
    from semantic3d.baselines.cnn.network import build_network

    config = CnnConfig()
    torch.manual_seed(0)
    network = build_network(config.cubes, config.network).eval().to(device)
    cubes = (torch.rand(batch, 5, 16, 16, 16, device=device) < 0.05).float()
    result: dict[str, Any] = {"batch": batch, "threads": torch.get_num_threads()}

    kind = "cuda" if device == "cuda" else "cpu"
    with torch.inference_mode():
        reference = network(cubes).float().argmax(1)
        plain = copy.deepcopy(network)
        network = network.to(memory_format=torch.channels_last_3d)

        def bf16() -> Any:
            with torch.autocast(kind, dtype=torch.bfloat16):
                return network(cubes)

        variants: dict[str, Callable[[], Any]] = {
            "eager_float32_ncdhw": lambda: plain(cubes),
            "eager_float32_channels_last": lambda: network(cubes),
            "bfloat16_autocast": bf16,
        }
        if device == "cuda":
            half = copy.deepcopy(network).half()
            variants["float16"] = lambda: half(cubes.half())
        forms = {}
        for mode in ("never", "always") if compile_network else ("never",):
            form = InferenceNetwork(
                network,
                device=device,
                precision="auto",
                compile=mode,
                batch_size=batch,
                logit_mask=torch.zeros(8, device=device),
            )
            name = f"labelling_form_{'compiled' if mode == 'always' else 'eager'}"
            _, first_s, _ = _timed(lambda form=form: form.classify(cubes), device)
            forms[name] = (form, first_s)
            variants[name] = lambda form=form: form.classify(cubes)
        for run in variants.values():
            run()  # warm
        times: dict[str, list[tuple[float, float]]] = {name: [] for name in variants}
        for _ in range(repeat):  # interleaved: a load change hits every variant alike
            for name, run in variants.items():
                times[name].append(_timed(run, device)[1:])
        for name in variants:
            wall, cpu = min(times[name])
            result[name] = _rate(batch, wall, cpu)
        agree = (bf16().float().argmax(1) == reference).float().mean()
        result["bfloat16_autocast"]["argmax_agreement"] = float(agree)
        for name, (form, first_s) in forms.items():
            index, _ = form.classify(cubes)
            result[name].update(
                first_call_s=first_s,
                dtype=str(form.dtype).removeprefix("torch."),
                compiled=form.compiled,
                argmax_agreement=float((index == reference).float().mean()),
            )
    element = 2 if device == "cuda" else 4
    result["floor"] = _floors(batch, floors, flops=network_flops(), moved=activation_bytes(element))
    return result


# -- predict --------------------------------------------------------------------------------
def _untrained_model(cubes: dict[str, Any], prediction: dict[str, Any]) -> Any:
    import torch

    from semantic3d import __version__
    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.cnn.model import CnnModel
    from semantic3d.baselines.cnn.network import build_network

    base = CnnConfig()
    config = dataclasses.replace(
        base,
        cubes=dataclasses.replace(base.cubes, **cubes),
        prediction=dataclasses.replace(base.prediction, **prediction),
    )
    torch.manual_seed(0)
    return CnnModel(
        build_network(config.cubes, config.network),
        config=config,
        label_values=tuple(range(1, 9)),
        training_scans=(),
        seed=0,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version=__version__,
    )


def child_predict(folder: str, device: str, options: str) -> None:
    """In a fresh process: predict every scan of ``folder``; print a JSON measurement."""
    from semantic3d.baselines.common.prediction import predict_scans
    from semantic3d.baselines.common.submission import find_scans_to_label

    chosen = json.loads(options)
    model = _untrained_model(chosen.get("cubes", {}), chosen.get("prediction", {})).to(device)
    scans = find_scans_to_label(Path(folder))
    with tempfile.TemporaryDirectory() as scratch:
        cpu, wall = time.process_time(), time.perf_counter()
        result = predict_scans(model, scans, Path(scratch) / "out")
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    peak = peak_rss_mb()  # VmHWM: ru_maxrss would hold the parent's size at the fork
    measured = _rate(result.n_points, wall, cpu)
    measured.update(
        scans=len(scans), peak_rss_mb=peak, compiled=model.inference.compiled, options=options
    )
    print(json.dumps(measured))


def _crop(path: Path, out: Path, edge_m: float) -> int:
    from semantic3d.io.ascii import write_ascii_points
    from semantic3d.io.formats import read_points

    cloud = read_points(path)
    xy = np.asarray(cloud.xyz)[:, :2]
    low = xy.min(axis=0)
    keep = np.all(xy < low + edge_m, axis=1)
    write_ascii_points(out, [cloud[keep]])
    return int(keep.sum())


def bench_predict(device: str, edge_m: float, floors: dict[str, Any]) -> dict[str, Any]:
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        names = sorted(p.stem for p in DATA.glob("*.txt"))
        if device == "cuda":
            for name in names:
                (folder / f"{name}.txt").symlink_to(DATA / f"{name}.txt")
        else:
            for name in names[:2]:
                _crop(DATA / f"{name}.txt", folder / f"{name}.txt", edge_m)
        runs: dict[str, dict[str, Any]] = {
            "point_centred": {},
            "corner_centred": {"cubes": {"centring": "corner"}},
        }
        if device == "cuda":
            eager = {"precision": "float32", "compile": "never"}
            runs["point_centred_float32_eager"] = {"prediction": eager}
        for name, options in runs.items():
            child = [sys.executable, __file__, "--child", str(folder), device, json.dumps(options)]
            done = subprocess.run(child, capture_output=True, text=True)
            if done.returncode != 0:  # the error goes in the report; the other runs go on
                results[name] = {"error": done.stderr.strip().splitlines()[-40:]}
                print(f"predict {name} failed:\n{done.stderr[-4000:]}", file=sys.stderr)
                continue
            results[name] = json.loads(done.stdout.strip().splitlines()[-1])
    points = next((r["points"] for r in results.values() if "points" in r), 0)
    element = 2 if device == "cuda" else 4
    results["floor"] = _floors(
        points, floors, flops=network_flops(), moved=activation_bytes(element)
    )
    return results


# -- train ----------------------------------------------------------------------------------
def bench_train(
    device: str, n_scans: int, n_batches: int, rotate_every: int, floors: dict[str, Any]
) -> dict[str, Any]:
    import contextlib

    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.cnn.rounds import make_round
    from semantic3d.baselines.cnn.training import _tile_scan, _training_classes, train_cnn_model
    from semantic3d.baselines.common.scans import find_labelled_scans

    base = CnnConfig()
    config = dataclasses.replace(
        base,
        training=dataclasses.replace(
            base.training, n_batches=n_batches, rotate_every=rotate_every, checkpoint_every=0
        ),
    )
    scans = find_labelled_scans(DATA)[:n_scans]
    names = tuple(s.name for s in scans)
    with contextlib.ExitStack() as stack:
        tiled = [stack.enter_context(_tile_scan(scan, config, None)) for scan in scans]
        classes = _training_classes(sum(s.counts.sum(axis=0) for s in tiled), config, names)
        make_round(tiled, classes, config, 0, 1, device=device)  # compiled, warm
        _, round_s, round_cpu = _timed(
            lambda: make_round(tiled, classes, config, 1, rotate_every, device=device), device
        )
    seen: list[tuple[int, float]] = []
    started = time.perf_counter()

    def progress(state: Any) -> None:
        if state.stage == "train":
            seen.append((state.batch, time.perf_counter() - started))

    _, wall, cpu = _timed(
        lambda: train_cnn_model(scans, config=config, device=device, progress=progress), device
    )
    # After the first round's cubes (no overlap possible): the steady rate.
    first = next(t for b, t in seen if b >= 1)
    steady = (seen[-1][0] - 1) / (seen[-1][1] - first)
    per_batch = 3 * network_flops() * config.training.batch_size
    return {
        "scans": n_scans,
        "batches": n_batches,
        "rotate_every": rotate_every,
        "wall_s": wall,
        "cpu_s": cpu,
        "batches_per_s": n_batches / wall,
        "steady_batches_per_s": steady,
        "batches_per_cpu_s": n_batches / cpu,
        "paper_schedule_s": PAPER_BATCHES / steady,
        "one_round_of_cubes_alone": {
            "wall_s": round_s,
            "cpu_s": round_cpu,
            "batches": rotate_every,
        },
        "floor": {
            "flops_per_batch": per_batch,
            "batch_floor_s": per_batch / floors["matmul_flops_per_s"],
            "paper_schedule_floor_s": PAPER_BATCHES * per_batch / floors["matmul_flops_per_s"],
        },
    }


# -- batch sizes and profiles (GPU) -----------------------------------------------------------
def bench_sweep(device: str, floors: dict[str, Any]) -> dict[str, Any]:
    """Cube kernels and the network at growing batches; where the time of a training step,
    a batch of cubes and a compiled network call goes (the profiler's top kernels)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    from semantic3d.baselines.cnn.config import CnnConfig, CubeConfig
    from semantic3d.baselines.cnn.cubes import build_occupancy, compute_corner_cells
    from semantic3d.baselines.cnn.cubes_torch import DeviceOccupancy
    from semantic3d.baselines.cnn.inference import InferenceNetwork
    from semantic3d.baselines.cnn.network import build_network
    from semantic3d.baselines.cnn.point_cubes_torch import DevicePointCubes
    from semantic3d.spatial.voxels import grid_origin

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    sort = "cuda_time_total" if device == "cuda" else "cpu_time_total"

    def top(run: Callable[[], Any], rows: int = 12) -> list[str]:
        with profile(activities=activities) as prof:
            run()
            _sync(device)
        return prof.key_averages().table(sort_by=sort, row_limit=rows).splitlines()

    result: dict[str, Any] = {}
    xyz = _load_xyz()
    cubes = CubeConfig(centring="point")
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=max(cubes.voxel_sizes_m))
    occupancy = build_occupancy(
        xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring="point"
    )
    corner = build_occupancy(xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m)
    held = DevicePointCubes(occupancy, device=device, cube_voxels=16)
    corners_held = DeviceOccupancy(corner, device=device, cube_voxels=16)
    rng = np.random.default_rng(1)
    sizes = (4096, 16384, 65536) if device == "cuda" else (256, 1024)

    def cube_rates(n: int) -> None:
        queries = xyz[rng.choice(len(xyz), min(n, len(xyz)), replace=False)]
        cells, fractions = held.anchors(queries)
        corner_cells = torch.as_tensor(
            compute_corner_cells(
                queries, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, cube_voxels=16
            ),
            device=device,
        )

        def point() -> Any:
            return held.fill(cells, fractions, dtype=torch.float16)

        def corner_fill() -> Any:
            return corners_held.fill(corner_cells, dtype=torch.float16)

        held.fill(cells[:64], fractions[:64], dtype=torch.float16)
        corners_held.fill(corner_cells[:64], dtype=torch.float16)
        point_s = _timed(point, device)[1]
        corner_s = _timed(corner_fill, device)[1]
        result[f"cubes_{n}"] = {
            "point_centred_points_per_s": len(queries) / point_s,
            "corner_centred_points_per_s": len(queries) / corner_s,
        }
        print(f"sweep cubes {n}: {result[f'cubes_{n}']}", flush=True)
        if n == sizes[0]:
            result["profile_point_cubes"] = top(point)

    for n in sizes:
        cube_rates(n)
    config = CnnConfig()
    torch.manual_seed(0)
    network = build_network(config.cubes, config.network).eval().to(device)
    for n in sizes[:2]:
        form = InferenceNetwork(
            network.to(memory_format=torch.channels_last_3d),
            device=device,
            precision="auto",
            compile="always" if device == "cuda" else "never",
            batch_size=n,
            logit_mask=torch.zeros(8, device=device),
        )
        batch = (torch.rand(n, 5, 16, 16, 16, device=device) < 0.05).to(form.dtype)
        with torch.inference_mode():
            _, first_s, _ = _timed(lambda form=form, batch=batch: form.classify(batch), device)
            best = min(
                _timed(lambda form=form, batch=batch: form.classify(batch), device)[1]
                for _ in range(5)
            )
            result[f"network_{n}"] = {"points_per_s": n / best, "first_call_s": first_s}
            if n == sizes[0]:
                result["profile_network"] = top(lambda form=form, batch=batch: form.classify(batch))
        print(f"sweep network {n}: {result[f'network_{n}']}", flush=True)
    # one training step's kernels (bfloat16 autocast on a GPU, as train runs it)
    train_net = build_network(config.cubes, config.network).to(device)
    optimizer = torch.optim.Adadelta(train_net.parameters())
    loss_fn = torch.nn.CrossEntropyLoss()
    cubes_b = (torch.rand(100, 5, 16, 16, 16, device=device) < 0.05).float()
    target = torch.randint(0, 8, (100,), device=device)

    def steps(k: int = 10) -> None:
        for _ in range(k):
            optimizer.zero_grad(set_to_none=True)
            with torch.autocast(device, dtype=torch.bfloat16, enabled=device == "cuda"):
                loss = loss_fn(train_net(cubes_b).float(), target)
            loss.backward()
            optimizer.step()

    timed_steps = 20 if device == "cuda" else 1
    for deterministic in (True, False):
        torch.backends.cudnn.deterministic = deterministic
        torch.backends.cudnn.benchmark = not deterministic
        steps(3 if device == "cuda" else 1)
        _, step_s, _ = _timed(lambda: steps(timed_steps), device)
        result[f"train_step_deterministic_{deterministic}_s"] = step_s / timed_steps
        if deterministic:
            result["profile_train_step"] = top(lambda: steps(timed_steps), rows=16)
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = False, False
    print(
        "sweep train step (s): deterministic "
        f"{result['train_step_deterministic_True_s']:.4f}, free "
        f"{result['train_step_deterministic_False_s']:.4f}",
        flush=True,
    )
    for name in ("profile_point_cubes", "profile_network", "profile_train_step"):
        print(name, "\n".join(result[name]), sep="\n", flush=True)
    return result


def _cpu_model() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return ""
    return next((line.split(":", 1)[1].strip() for line in lines if "model name" in line), "")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child_predict(sys.argv[2], sys.argv[3], sys.argv[4])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--only", default="floors,cubes,network,predict,train")
    parser.add_argument("--quick", action="store_true", help="smaller sizes, no compilation")
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled network")
    parser.add_argument("--data", type=Path, default=DATA, help="the Oakland samples' folder")
    args = parser.parse_args()
    set_data(args.data)
    if not DATA.is_dir():
        sys.exit(f"{DATA}: the Oakland samples are not here")
    cuda = args.device == "cuda"
    only = set(args.only.split(","))
    report: dict[str, Any] = {
        "device": args.device,
        "cpu": os.cpu_count(),
        "cpu_model": _cpu_model(),
        "load_average": os.getloadavg(),
    }
    if cuda:
        import torch

        report["gpu"] = torch.cuda.get_device_name()

    def section(name: str, run: Callable[[], Any]) -> None:
        report[name] = run()
        print(name, json.dumps(report[name], indent=1), flush=True)

    floors = bench_floors(args.device, args.quick)
    report["floors"] = floors
    print("floors", json.dumps(floors, indent=1), flush=True)
    queries = (4096 if cuda else 1000) // (4 if args.quick else 1)
    if "cubes" in only:
        if not cuda:
            section("corner_cubes", lambda: bench_cubes(queries))
        section("point_cubes", lambda: bench_point_cubes(_load_xyz(), queries, args.device, floors))
        section(
            "point_cubes_dense",
            lambda: bench_point_cubes(dense_surfaces(), queries // 4, args.device, floors),
        )
    if "network" in only:
        batch = 4096 if cuda else 256
        section(
            "network",
            lambda: bench_network(
                args.device, batch, 5 if cuda else 4, not (args.quick or args.no_compile), floors
            ),
        )
    if "sweep" in only:
        section("sweep", lambda: bench_sweep(args.device, floors))
    if "predict" in only:
        section("predict", lambda: bench_predict(args.device, 4.0 if args.quick else 6.0, floors))
    if "train" in only:
        if cuda:
            section("train", lambda: bench_train("cuda", 10, 1000, 100, floors))
        else:
            batches = 6 if args.quick else 20
            section("train", lambda: bench_train("cpu", 2, batches, batches // 2, floors))
    report["load_average_end"] = os.getloadavg()
    OUT.mkdir(exist_ok=True)
    path = OUT / ("bench_cnn_cuda.json" if cuda else "bench_cnn.json")
    previous = json.loads(path.read_text()) if path.is_file() else {}
    path.write_text(json.dumps({**previous, **report}, indent=2) + "\n")  # sections merge
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
