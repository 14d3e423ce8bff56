"""The RandLA-Net baseline measured: accuracy on scans never seen, speed, FLOPs and memory.

Sections (``--sections``, comma separated; default all):

- ``cv``: scan-grouped 5-fold cross-validation on the 10 shared CMU Oakland scans (Munoz
  et al., CVPR 2009), the folds of ``cv_covariance.py`` (seed ``s``: the scans in the
  order ``numpy.random.default_rng(s).permutation(10)``, fold ``f`` holds out positions
  ``f, f + 5``). Each (seed, fold) trains RandLA-Net on the other 8 scans with training
  seed ``s`` and labels every point of the 2 held-out scans; the covariance baseline (the
  library default, sampling seed ``s``) is trained and scored on the same folds. Per seed
  the confusion matrices of the folds run are pooled; the table gives mean ± std over
  seeds; RandLA-Net is scored twice, with one pass per block and with ``VOTES`` passes
  averaged (``[prediction] votes``). ``--folds`` and ``--seeds`` run a part (say which in
  the report); results are written after every fold (merged with the folds other
  processes wrote to the same file meanwhile), and a rerun skips the (seed, fold) pairs
  already in the file.
- ``sim``: train on one simulated terrestrial scan (``semantic3d simulate``), label
  another scene; both baselines.
- ``speed``: ``predict`` end to end (read, tile, voxels, network, ``.labels`` and run
  record) on one Oakland scan, in points per wall and CPU second, against the covariance
  baseline in the same run; the network's multiply-adds per point (torch's FLOP counter)
  against the machine's measured matrix-product rate.
- ``memory``: peak RSS of ``predict`` (a fresh process each) on simulated scans of growing
  size: flat in scan size when memory is bounded by a tile.

Nothing is tuned on a fold's test scans: the configuration is the ``cpu`` preset as
shipped, or with ``--config FILE.toml`` a candidate (``benchmarks/randla_candidates/``),
whose folds are the same and whose results go to ``bench_randla_cv_<FILE>.json``.
Usage: ``python benchmarks/bench_randla.py --sections cv --seeds 0 --jobs 2``; ``--quick``
runs a small version of every section.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

# OpenMP workers that busy-wait after each parallel region starve the other core of a
# 2-core machine (a 10x slowdown of the network measured); semantic3d sets this on import,
# but the pool's children import torch first.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

ROOT = Path(__file__).resolve().parents[1]
OAKLAND = ROOT.parent / "shared" / "data" / "oakland"
OUT = ROOT / "benchmarks" / "out"
N_FOLDS = 5
VOTES = 4  # cv: RandLA-Net is also scored with this many passes averaged


def _load() -> float:
    return os.getloadavg()[0]


# -- cross-validation -------------------------------------------------------------------
def fold_scans(seed: int, names: list[str]) -> list[list[str]]:
    """The held-out scans of each fold, as ``cv_covariance.py`` draws them."""
    order = np.random.default_rng(seed).permutation(len(names))
    return [[names[int(i)] for i in order[fold::N_FOLDS]] for fold in range(N_FOLDS)]


def _label_scan(predictor: Any, scan: Any, workdir: Path) -> tuple[np.ndarray, int]:
    """The ``(8, 8)`` confusion matrix of one scan labelled by ``predictor``."""
    from semantic3d.io.formats import iter_points
    from semantic3d.metrics import ConfusionMatrix

    truth = np.concatenate(list(scan.iter_labels()))
    matrix = ConfusionMatrix()
    with tempfile.TemporaryDirectory(dir=workdir) as scratch:
        chunks = iter_points(scan.points_path, chunk_size=predictor.chunk_size)
        for block in predictor.iter_labelled_blocks(chunks, workdir=Path(scratch)):
            matrix.update(truth[block.point_indices], block.labels)
    return matrix.compute(), truth.size


def run_fold(task: tuple[int, int, int | None, str, str, str | None]) -> dict[str, Any]:
    """Train both baselines on one fold's training scans, score its held-out scans."""
    seed, fold, batches, workdir, data, config_path = task
    import dataclasses

    import torch

    from semantic3d.baselines.common.scans import find_labelled_scans
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.training import train_covariance_model
    from semantic3d.baselines.randla.config import load_config, preset_config
    from semantic3d.baselines.randla.training import train_randla_model

    torch.set_num_threads(1)
    scans = find_labelled_scans(data)
    held_out = fold_scans(seed, [s.name for s in scans])[fold]
    train = [s for s in scans if s.name not in held_out]
    test = [s for s in scans if s.name in held_out]
    config = preset_config("cpu") if config_path is None else load_config(config_path)
    changes: dict[str, Any] = {"seed": seed}
    if batches is not None:
        changes["n_batches"] = batches
    config = dataclasses.replace(config, training=dataclasses.replace(config.training, **changes))
    result: dict[str, Any] = {"seed": seed, "fold": fold, "test_scans": held_out}
    if config_path is not None:
        result["config"] = Path(config_path).read_text()
    started, cpu = time.perf_counter(), time.process_time()
    model = train_randla_model(train, config=config, workdir=workdir)
    result["randla_train_s"] = time.perf_counter() - started
    result["randla_train_cpu_s"] = time.process_time() - cpu
    cpu = time.process_time()
    matrices = [_label_scan(model, scan, Path(workdir)) for scan in test]
    result["randla_predict_cpu_s"] = time.process_time() - cpu
    result["randla_confusion"] = sum(m for m, _ in matrices).tolist()
    result["n_points"] = sum(n for _, n in matrices)
    # the same model, its probabilities averaged over VOTES turned and resampled passes
    cpu = time.process_time()
    model.configure_prediction(votes=VOTES)
    result[f"randla_votes{VOTES}_confusion"] = sum(
        _label_scan(model, scan, Path(workdir))[0] for scan in test
    ).tolist()
    result[f"randla_votes{VOTES}_predict_cpu_s"] = time.process_time() - cpu
    covariance = CovarianceConfig()
    covariance = dataclasses.replace(
        covariance, sampling=dataclasses.replace(covariance.sampling, seed=seed)
    )
    cpu = time.process_time()
    cov_model = train_covariance_model(train, config=covariance)
    result["covariance_train_cpu_s"] = time.process_time() - cpu
    result["covariance_confusion"] = sum(
        _label_scan(cov_model, scan, Path(workdir))[0] for scan in test
    ).tolist()
    result["load"] = _load()
    return result


def cross_validate(
    seeds: list[int],
    folds: list[int],
    batches: int | None,
    jobs: int,
    out: Path,
    data: Path,
    config: Path | None = None,
) -> dict[str, Any]:
    """Run the missing (seed, fold) pairs, save each as it ends; summarise."""
    import multiprocessing

    done: list[dict[str, Any]] = json.loads(out.read_text())["runs"] if out.is_file() else []
    have = {(r["seed"], r["fold"]) for r in done}
    workdir = tempfile.mkdtemp(prefix="bench-randla-")
    tasks = [
        (s, f, batches, workdir, str(data), None if config is None else str(config))
        for s in seeds
        for f in folds
        if (s, f) not in have
    ]
    print(f"cv: {len(tasks)} fold runs to do ({len(have)} in {out}), load {_load():.1f}")
    env = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    os.environ.update(env)
    context = multiprocessing.get_context("spawn")
    with context.Pool(max(1, jobs)) as pool:
        for result in pool.imap_unordered(run_fold, tasks):
            # another run may have written folds to the same file meanwhile: keep them
            done = _merged(json.loads(out.read_text())["runs"] if out.is_file() else [], done)
            done.append(result)
            _write(out, {"runs": done, "summary": summarise(done)})
            print(
                f"  seed {result['seed']} fold {result['fold']}: RandLA mIoU "
                f"{_scores(result['randla_confusion']).mean_iou:.3f}, covariance "
                f"{_scores(result['covariance_confusion']).mean_iou:.3f} "
                f"(train {result['randla_train_s']:.0f} s, load {result['load']:.1f})",
                flush=True,
            )
    summary = summarise(done)
    _write(out, {"runs": done, "summary": summary})
    return summary


def _merged(stored: list[dict[str, Any]], ours: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs of both lists, one per (seed, fold), ours first."""
    keys = {(r["seed"], r["fold"]) for r in ours}
    return ours + [r for r in stored if (r["seed"], r["fold"]) not in keys]


def _scores(confusion: Any) -> Any:
    from semantic3d.metrics.scores import compute_scores

    return compute_scores(np.asarray(confusion, np.int64))


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per seed: the pooled scores of its folds; over seeds: mean and std."""
    from semantic3d.core import CLASSES

    summary: dict[str, Any] = {}
    methods = ["randla", "covariance"]
    if runs and all(f"randla_votes{VOTES}_confusion" in r for r in runs):
        methods.append(f"randla_votes{VOTES}")
    for method in methods:
        per_seed: dict[int, Any] = {}
        folds: dict[int, list[int]] = {}
        for run in runs:
            matrix = np.asarray(run[f"{method}_confusion"], np.int64)
            per_seed[run["seed"]] = per_seed.get(run["seed"], 0) + matrix
            folds.setdefault(run["seed"], []).append(run["fold"])
        scores = {seed: _scores(matrix) for seed, matrix in sorted(per_seed.items())}
        mious = [s.mean_iou for s in scores.values()]
        summary[method] = {
            "folds_per_seed": {str(k): sorted(v) for k, v in folds.items()},
            "miou_per_seed": {str(k): s.mean_iou for k, s in scores.items()},
            "oa_per_seed": {str(k): s.overall_accuracy for k, s in scores.items()},
            "miou_mean": float(np.mean(mious)) if mious else None,
            "miou_std": float(np.std(mious)) if mious else None,
            "oa_mean": float(np.mean([s.overall_accuracy for s in scores.values()]))
            if scores
            else None,
            "iou_mean": {
                c.name: float(np.nanmean([s.iou[c.value - 1] for s in scores.values()]))
                for c in CLASSES
                if c.value != 7
            }
            if scores
            else {},
        }
    summary["randla_train_s_mean"] = float(np.mean([r["randla_train_s"] for r in runs]))
    summary["randla_train_cpu_s_mean"] = float(np.mean([r["randla_train_cpu_s"] for r in runs]))
    return summary


# -- simulated scenes ---------------------------------------------------------------------
def simulated_transfer(
    n_points: int, batches: int | None, folder: Path, threads: int = 1
) -> dict[str, Any]:
    """Train on one simulated scene, label another (both ways), both baselines; torch on
    ``threads`` threads."""
    import dataclasses

    import torch

    from semantic3d.baselines.common.scans import find_labelled_scans
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.training import train_covariance_model
    from semantic3d.baselines.randla.config import preset_config
    from semantic3d.baselines.randla.training import train_randla_model
    from semantic3d.datasets.simulator import simulate

    torch.set_num_threads(max(1, threads))
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for scene, seed in (("street", 1), ("village", 2)):
        name = f"{scene}{seed}"
        names.append(name)
        if not (folder / f"{name}.txt").is_file():
            scan = simulate(scene, out=folder / name, n_points=n_points, seed=seed).scans[0]
            scan.points_path.rename(folder / f"{name}.txt")
            scan.labels_path.rename(folder / f"{name}.labels")
    scans = {s.name: s for s in find_labelled_scans(folder)}
    config = preset_config("cpu")
    if batches is not None:
        config = dataclasses.replace(
            config, training=dataclasses.replace(config.training, n_batches=batches)
        )
    results: dict[str, Any] = {"n_points": n_points, "load_start": _load()}
    for train_name, test_name in ((names[0], names[1]), (names[1], names[0])):
        started = time.perf_counter()
        model = train_randla_model([scans[train_name]], config=config, workdir=folder)
        train_s = time.perf_counter() - started
        randla = _scores(_label_scan(model, scans[test_name], folder)[0])
        covariance = train_covariance_model([scans[train_name]], config=CovarianceConfig())
        cov = _scores(_label_scan(covariance, scans[test_name], folder)[0])
        results[f"{train_name}->{test_name}"] = {
            "randla": {"miou": randla.mean_iou, "oa": randla.overall_accuracy},
            "covariance": {"miou": cov.mean_iou, "oa": cov.overall_accuracy},
            "randla_train_s": train_s,
        }
        print(
            f"sim {train_name} -> {test_name}: RandLA {randla.mean_iou:.3f} / "
            f"{randla.overall_accuracy:.3f}, covariance {cov.mean_iou:.3f} / "
            f"{cov.overall_accuracy:.3f} (train {train_s:.0f} s)",
            flush=True,
        )
    results["load_end"] = _load()
    return results


# -- speed ------------------------------------------------------------------------------------
def _matmul_rate(threads: int) -> float:
    """FP32 multiply-add rate of this machine's torch matrix product (FLOP/s, 2 per FMA)."""
    import torch

    torch.set_num_threads(threads)
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    a @ b
    cpu, n = time.process_time(), 0
    while time.process_time() - cpu < 1.0:
        a @ b
        n += 1
    return 2 * 1024**3 * n / (time.process_time() - cpu) * threads


def flops_per_point(model: Any, n_points: int = 16384) -> dict[str, float]:
    """Multiply-adds of one pass over a block of ``n_points`` (torch's FLOP counter counts
    the matrix products; the gathers, softmaxes and norms are memory-bound extras)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from semantic3d.baselines.randla.levels import build_levels, stack_levels

    network = model.config.network
    xyz = np.random.default_rng(0).uniform(-10, 10, (n_points, 3)).astype(np.float32)
    features = np.concatenate(
        [xyz, np.zeros((n_points, model.config.inputs.n_inputs - 3), np.float32)], axis=1
    )
    levels = build_levels(xyz, k=network.k_neighbours, ratios=network.ratios, device="cpu")
    batch = stack_levels([xyz], [levels], device="cpu")
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        model.network(torch.from_numpy(features), batch)
    return {"flops_per_point": counter.get_total_flops() / n_points, "block_points": n_points}


_CHILD = """
import json, resource, sys
from semantic3d.cli.app import app
try:
    code = app(sys.argv[1:], standalone_mode=False)
    if isinstance(code, int) and code:  # a refusal returns its exit code here
        sys.exit(code)
finally:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    with open("/proc/self/status") as status:
        peak = next(int(line.split()[1]) for line in status if line.startswith("VmHWM"))
    print(json.dumps({"cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mib": peak / 1024}))
"""
"""A fresh interpreter running one command and printing its CPU time and peak RSS (VmHWM:
``ru_maxrss`` survives ``execve`` and would report the parent's peak)."""


def _predict_command(model: Path, scan: Path, out: Path, baseline: str, *extra: str) -> list[str]:
    """``predict`` of one scan, or of every scan of a folder (``scan`` a folder)."""
    where = ["--data", str(scan)] if scan.is_dir() else [str(scan)]
    return [
        sys.executable, "-c", _CHILD, "baseline", baseline, "predict", *where,
        "--model", str(model), "--out", str(out), "--overwrite", *extra,
    ]  # fmt: skip


def _timed_run(command: list[str], env: dict[str, str]) -> dict[str, float]:
    """Wall seconds, and CPU seconds and peak RSS (MiB) of a fresh process running a command."""
    started = time.perf_counter()
    done = subprocess.run(command, env={**os.environ, **env}, capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"{' '.join(command[3:])} failed:\n{done.stderr[-3000:]}")
    wall = time.perf_counter() - started
    measured: dict[str, float] = json.loads(done.stdout.strip().splitlines()[-1])
    return {"wall_s": wall, **measured}


def speed(folder: Path, batches: int, data: Path, model_file: Path | None) -> dict[str, Any]:
    """End-to-end ``predict --data`` of the 10 Oakland scans (1 M points) by both
    baselines, each a fresh process with its model loaded once (the models trained on the
    first 8 scans, or ``model_file``)."""
    import dataclasses

    import torch

    from semantic3d.baselines.common.scans import find_labelled_scans
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.persistence import save_model as save_covariance
    from semantic3d.baselines.covariance.training import train_covariance_model
    from semantic3d.baselines.randla.config import preset_config
    from semantic3d.baselines.randla.persistence import save_model
    from semantic3d.baselines.randla.training import train_randla_model

    torch.set_num_threads(1)
    folder.mkdir(parents=True, exist_ok=True)
    scans = find_labelled_scans(data)
    config = preset_config("cpu")
    config = dataclasses.replace(
        config, training=dataclasses.replace(config.training, n_batches=batches)
    )
    model_path = folder / "speed.rla"
    if model_file is not None:
        from semantic3d.baselines.randla.persistence import load_model

        model = load_model(model_file)
    else:
        model = train_randla_model(scans[:8], config=config, workdir=folder)
    save_model(model, model_path)
    cov_path = folder / "speed.s3d"
    save_covariance(train_covariance_model(scans[:8], config=CovarianceConfig()), cov_path)
    n_points = sum(sum(part.size for part in s.iter_labels()) for s in scans)
    results: dict[str, Any] = {"data": str(data), "n_points": n_points, "load_start": _load()}
    for threads in (1, 2):
        env = {"OMP_NUM_THREADS": str(threads), "NUMBA_NUM_THREADS": str(threads)}
        for name, path, baseline in (
            ("randla", model_path, "randla"),
            ("covariance", cov_path, "covariance"),
        ):
            extra = ("--parallel-scans", "1") if baseline == "covariance" and threads == 1 else ()
            command = _predict_command(path, data, folder / name, baseline, *extra)
            run = _timed_run(command, env)
            run["points_per_s"] = n_points / run["wall_s"]
            run["points_per_cpu_s"] = n_points / run["cpu_s"]
            results[f"{name}_threads{threads}"] = run
            print(
                f"speed {name}, {threads} thread(s): {run['points_per_s']:,.0f} points/s "
                f"({run['points_per_cpu_s']:,.0f} per CPU-s), {run['peak_rss_mib']:.0f} MiB, "
                f"load {_load():.1f}",
                flush=True,
            )
    results["flops"] = flops_per_point(model)
    results["matmul_flops_per_s_1_thread"] = _matmul_rate(1)
    results["load_end"] = _load()
    return results


# -- memory in scan size ----------------------------------------------------------------------
def memory(sizes: list[int], folder: Path, model_path: Path) -> dict[str, Any]:
    """Peak RSS and throughput of ``predict`` on simulated scans of ``sizes`` points."""
    from semantic3d.datasets.simulator import simulate

    folder.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"runs": []}
    for n_points in sizes:
        scan_path = folder / f"square{n_points}.txt"
        if not scan_path.is_file():
            scan = simulate("square", out=folder / f"sim{n_points}", n_points=n_points, seed=5)
            scan.scans[0].points_path.rename(scan_path)
        env = {"OMP_NUM_THREADS": "2", "NUMBA_NUM_THREADS": "2"}
        out = folder / "predicted" / f"square{n_points}.labels"  # never beside the scan
        run = _timed_run(_predict_command(model_path, scan_path, out, "randla"), env)
        written = sum(1 for _ in out.open("rb"))
        run.update(n_points=written, points_per_s=written / run["wall_s"], load=_load())
        results["runs"].append(run)
        print(
            f"memory: {written:,} points, peak RSS {run['peak_rss_mib']:.0f} MiB, "
            f"{run['points_per_s']:,.0f} points/s (load {run['load']:.1f})",
            flush=True,
        )
        out.unlink()
        out.with_name(out.name + ".json").unlink(missing_ok=True)
    return results


# -- on a device ------------------------------------------------------------------------------
def _untrained(preset: str, changes: dict[str, dict[str, Any]]) -> Any:
    """A model of ``preset`` (with ``changes`` per table) and untrained weights: speed does
    not depend on the weights."""
    import torch

    from semantic3d import __version__
    from semantic3d.baselines.randla.config import config_from_dict
    from semantic3d.baselines.randla.model import RandlaModel
    from semantic3d.baselines.randla.network import build_network

    config = config_from_dict({"preset": preset, **changes})
    torch.manual_seed(0)
    values = (1, 2, 3, 4, 5, 6, 8)
    network = build_network(config.inputs.n_inputs, len(values), config.network)
    return RandlaModel(
        network,
        config=config,
        label_values=values,
        training_scans=(),
        seed=0,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version=__version__,
    )


def device_speed(
    folder: Path,
    data: Path,
    device: str,
    sim_points: int,
    batches: int,
    parts: tuple[str, ...] = ("predict", "train"),
) -> dict[str, Any]:
    """``predict --device DEVICE`` end to end (a fresh process) on the Oakland scans and on
    one simulated scan of ``sim_points``, for the ``cpu`` preset's network and the paper's
    (colour off: the scans have none), untrained; training batches per second of both on
    8 Oakland scans; FLOPs per point against the device's measured matrix rate."""
    import dataclasses

    import torch

    from semantic3d.baselines.common.scans import find_labelled_scans
    from semantic3d.baselines.randla.persistence import save_model
    from semantic3d.baselines.randla.training import train_randla_model
    from semantic3d.datasets.simulator import simulate

    folder.mkdir(parents=True, exist_ok=True)
    scan_path = folder / f"street{sim_points}.txt"
    if "predict" in parts and not scan_path.is_file():
        scan = simulate("street", out=folder / f"sim{sim_points}", n_points=sim_points, seed=3)
        scan.scans[0].points_path.rename(scan_path)
    results: dict[str, Any] = {"device": device, "load_start": _load()}
    if device == "cuda":
        results["gpu"] = torch.cuda.get_device_name()
        a = torch.randn(8192, 8192, device=device, dtype=torch.bfloat16)
        a @ a
        torch.cuda.synchronize()
        started = time.perf_counter()
        for _ in range(5):
            a @ a
        torch.cuda.synchronize()
        results["matmul_bf16_flops_per_s"] = 5 * 2 * 8192**3 / (time.perf_counter() - started)
    presets = {
        "cpu": {},
        "paper": {"inputs": {"rgb": False}},
        "paper_large_blocks": {"inputs": {"rgb": False}, "blocks": {"max_points": 262144}},
    }
    scans = find_labelled_scans(data)
    for name, changes in presets.items():
        model = _untrained(name.split("_")[0], changes)
        path = folder / f"{name}.rla"
        save_model(model, path)
        row: dict[str, Any] = {"flops": flops_per_point(model)}
        targets = ((data, None), (scan_path, sim_points)) if "predict" in parts else ()
        for target, n_points in targets:
            out = folder / f"{name}-{target.stem}"
            if target.is_file():
                out = out.with_suffix(".labels")
            command = _predict_command(path, target, out, "randla", "--device", device)
            try:
                run = _timed_run(command, {})
            except RuntimeError as error:
                row[target.stem] = {"error": str(error).splitlines()[-20:]}
                print(f"speed {name} on {target.name} {error}")
                continue
            if n_points is None:
                n_points = sum(sum(part.size for part in s.iter_labels()) for s in scans)
            run.update(n_points=n_points, points_per_s=n_points / run["wall_s"])
            row[target.stem] = run
            print(
                f"device speed {name} on {target.name}: {run['points_per_s']:,.0f} points/s, "
                f"{run['peak_rss_mib']:.0f} MiB, {run['wall_s']:.1f} s",
                flush=True,
            )
        if name != "paper_large_blocks" and "train" in parts:
            config = dataclasses.replace(
                model.config,
                training=dataclasses.replace(
                    model.config.training, n_batches=batches, checkpoint_every=0
                ),
            )
            marks: list[tuple[str, float]] = []
            started = time.perf_counter()

            def progress(
                state: Any, marks: list[tuple[str, float]] = marks, started: float = started
            ) -> None:
                marks.append((state.stage, time.perf_counter() - started))

            train_randla_model(
                scans[:8], config=config, device=device, workdir=folder, progress=progress
            )
            wall = time.perf_counter() - started
            drawing = sum(
                later - at
                for (stage, at), (_, later) in itertools.pairwise(marks)
                if stage == "clouds"
            )
            row["train"] = {
                "batches": batches,
                "wall_s": wall,
                "batches_per_s": batches / wall,
                "drawing_clouds_s": drawing,
            }
            print(f"device train {name}: {row['train']}", flush=True)
        results[name] = row
    results["load_end"] = _load()
    return results


def _write(path: Path, document: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(path.name + ".partial")
    temp.write_text(json.dumps(document, indent=2) + "\n")
    temp.replace(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", default="cv,sim,speed,memory")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--folds", default="0,1,2,3,4")
    parser.add_argument("--batches", type=int, default=None, help="override n_batches")
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="cv: a candidate configuration (TOML) in place of the cpu preset; results in "
        "bench_randla_cv_<its name>.json",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=2,
        help="cv: fold runs at a time (processes); sim: torch threads",
    )
    parser.add_argument("--sizes", default="1000000,4000000,16000000")
    parser.add_argument("--sim-points", type=int, default=500_000)
    parser.add_argument("--model", type=Path, default=None, help="speed: this model, untrained")
    parser.add_argument("--data", type=Path, default=OAKLAND, help="the Oakland scans")
    parser.add_argument("--quick", action="store_true", help="a small version of every section")
    parser.add_argument("--device", default="cpu", help="device: where the device section runs")
    parser.add_argument("--device-parts", default="predict,train", help="device: what it runs")
    parser.add_argument(
        "--workdir", type=Path, default=Path(tempfile.gettempdir()) / "bench-randla"
    )
    args = parser.parse_args()
    sections = args.sections.split(",")
    if args.quick:
        args.seeds, args.folds, args.batches = "0", "0", args.batches or 20
        args.sizes, args.sim_points = "200000,800000", 100_000
    if "cv" in sections and not args.data.is_dir():
        print(f"cv: {args.data} not found, skipped")
        sections.remove("cv")
    if "cv" in sections:
        name = "bench_randla_cv_quick.json" if args.quick else "bench_randla_cv.json"
        if args.config is not None:
            name = name.replace(".json", f"_{args.config.stem}.json")
        summary = cross_validate(
            [int(s) for s in args.seeds.split(",")],
            [int(f) for f in args.folds.split(",")],
            args.batches,
            args.jobs,
            OUT / name,
            args.data,
            args.config,
        )
        for method in [m for m in ("randla", "covariance", f"randla_votes{VOTES}") if m in summary]:
            row = summary[method]
            print(
                f"{method}: mIoU {row['miou_mean']:.3f} ± {row['miou_std']:.3f}, OA "
                f"{row['oa_mean']:.3f} (seeds {row['folds_per_seed']})"
            )
    results: dict[str, Any] = {}
    if "sim" in sections:
        results["sim"] = simulated_transfer(
            args.sim_points, args.batches, args.workdir / "sim", args.jobs
        )
    if "speed" in sections and args.data.is_dir():
        results["speed"] = speed(args.workdir / "speed", args.batches or 300, args.data, args.model)
    if "device" in sections:
        results[f"device_{args.device}"] = device_speed(
            args.workdir / "device",
            args.data,
            args.device,
            args.sim_points,
            args.batches or 100,
            tuple(args.device_parts.split(",")),
        )
    if "memory" in sections:
        model_path = args.workdir / "speed" / "speed.rla"
        if not model_path.is_file():
            results["speed"] = speed(
                args.workdir / "speed", args.batches or 300, args.data, args.model
            )
        sizes = [int(s) for s in args.sizes.split(",")]
        results["memory"] = memory(sizes, args.workdir / "memory", model_path)
    if results:  # sections run now replace their earlier results; the others are kept
        path = OUT / ("bench_randla_quick.json" if args.quick else "bench_randla.json")
        earlier = json.loads(path.read_text()) if path.is_file() else {}
        _write(path, {**earlier, **results})


if __name__ == "__main__":
    main()
