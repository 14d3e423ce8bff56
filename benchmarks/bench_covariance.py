"""Throughput, memory and accuracy of the 3D covariance baseline, against the usual peers.

Sections (``--only features,forest,predict,memory,density,accuracy,peers``; default all
but density):

- features: multi-scale features (pyramid + k-NN + eigen features) in points/s, against
  pgeof run level by level on the same pyramid (k-NN + its features), pgeof at one scale
  on the full-resolution points, and jakteristics computing the same number of scales by
  radius (radius 2x each level's voxel size; large radii timed on a subsample of query
  points against the full cloud, per-point cost extrapolated).
- forest: class probabilities of the compiled forest vs ``RandomForestClassifier``
  ``predict_proba`` (n_jobs=-1) on the same rows, and the fit time.
- predict: end to end (read ASCII -> features -> classify -> write .labels), points/s, in
  memory and tiled.
- memory: peak RSS of tiled prediction of 1x and 4x larger scans (subprocesses).
- density: peak RSS and points/s of tiled prediction (a fresh process each, every core)
  of one simulated street station sampled more and more densely (``--density-points``,
  default 5, 10, 20 and 40 M points; above 4 M, so tiled): the same scene, so the tiles
  near the scanner grow with the scan, as a terrestrial scan's do; the growth in MiB a
  million points between sizes. (Copies side by side, above, grow the tiles' number.)
- accuracy: CMU Oakland (Munoz et al., CVPR 2009), train on 6 scans, validate on 4,
  per-class IoU, mIoU and OA for the multi-scale pyramid, single scales and per-point mode.
- peers: end to end on a folder of scans in one process (read ASCII, features, classify,
  write .labels for the 4 Oakland validation scans), points/s, CPU time and peak RSS of a
  fresh process each, and the rate of labelling alone (after start-up and model loading);
  ours one scan at a time and two at a time (``parallel_scans=2``, the CLI's default),
  against the pipeline a user assembles from jakteristics (its 27 features at radii
  0.25, 0.5, 1, 2 m + height above the scan's lowest point) and a
  scikit-learn forest (50 trees, depth 20) trained on the same class-balanced sample
  size; both models trained on the same 6 scans, and their mIoU / OA on the 4 scans.

Every timing is the best of ``--repeat`` runs (the machine may be shared). Needs the
real samples in ../shared/data; pgeof and jakteristics are optional peers
(``pip install pgeof jakteristics``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from semantic3d.baselines.covariance.config import (
    CovarianceConfig,
)
from semantic3d.baselines.covariance.predict import describe_hardware, predict_scan
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.core import CLASSES, PointCloud
from semantic3d.features import FeatureConfig, build_cloud_pyramid, compute_multiscale_features
from semantic3d.io.ascii import read_ascii_points, write_ascii_points
from semantic3d.io.labels import read_labels
from semantic3d.metrics import ConfusionMatrix

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import peak_rss_mb

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
NINE = [
    "eigenvalue_sum",
    "omnivariance",
    "eigenentropy",
    "anisotropy",
    "planarity",
    "linearity",
    "surface_variation",
    "sphericity",
    "verticality",
]
"""jakteristics' names of the covariance features we compute."""
TRAIN = ("ac", "ad", "ae", "ag", "ah", "ai")
VALIDATE = ("aj", "ak", "al", "ao")


def rate(n: int, seconds: float) -> str:
    return f"{n / seconds / 1e3:8.0f} k points/s"


def peak_rss_mib() -> float:
    return peak_rss_mb()  # VmHWM: a child's ru_maxrss holds its parent's size at the fork


def interleaved(repeat: int, contenders: dict[str, Callable[[], Any]]) -> dict[str, float]:
    """Best wall time of each contender, runs interleaved (A B C A B C ...) so that load
    from other processes on a shared machine hits all of them alike. The best CPU time
    (all threads of this process) of each is kept in ``CPU_SECONDS``: on a loaded machine
    it moves less than the wall time."""
    best = dict.fromkeys(contenders, float("inf"))
    for _ in range(repeat):
        for name, run in contenders.items():
            started, cpu_started = time.perf_counter(), time.process_time()
            run()
            best[name] = min(best[name], time.perf_counter() - started)
            CPU_SECONDS[name] = min(
                CPU_SECONDS.get(name, float("inf")), time.process_time() - cpu_started
            )
    return best


CPU_SECONDS: dict[str, float] = {}


def bench_features(cloud: PointCloud, name: str, repeat: int) -> None:
    config = FeatureConfig()
    per_point = dataclasses.replace(config, per_point=True)
    n = cloud.n_points
    print(f"\n== features: {name}, {n} points, {config.n_levels} levels, k={config.k_neighbours}")
    compute_multiscale_features(cloud[:2000], config=config)  # compile
    compute_multiscale_features(cloud[:2000], config=per_point)
    pyramid = build_cloud_pyramid(cloud, config=config)
    print("pyramid voxels per level:", [lv.n_voxels for lv in pyramid.levels])
    contenders: dict[str, Callable[[], Any]] = {
        "ours, voxel queries (default)": lambda: compute_multiscale_features(cloud, config=config),
        "ours, per-point queries": lambda: compute_multiscale_features(cloud, config=per_point),
    }
    try:
        import pgeof
    except ImportError:
        print("pgeof not installed: skipped")
    else:
        full = (cloud.xyz - cloud.xyz[0]).astype(np.float32)

        def pgeof_levels() -> None:
            # the same voxel pyramid (our build, timed), then pgeof's k-NN + features per level
            for level in build_cloud_pyramid(cloud, config=config).levels:
                xyz = level.xyz.astype(np.float32)
                k = min(config.k_neighbours, len(xyz))
                nn, _ = pgeof.knn_search(xyz, xyz, k)
                ptr = np.arange(0, len(xyz) * k + 1, k, dtype=np.uint32)
                pgeof.compute_features(xyz, nn.ravel().astype(np.uint32), ptr, k)

        def pgeof_one_scale() -> None:
            nn, _ = pgeof.knn_search(full, full, 10)
            ptr = np.arange(0, n * 10 + 1, 10, dtype=np.uint32)
            pgeof.compute_features(full, nn.ravel().astype(np.uint32), ptr, 10)

        contenders["pyramid + pgeof level by level"] = pgeof_levels
        contenders["pgeof one scale, full res, k=10"] = pgeof_one_scale
    best = interleaved(repeat, contenders)
    for label, seconds_taken in best.items():
        print(
            f"{label:34s} {rate(n, seconds_taken)}  ({seconds_taken:.2f} s, "
            f"CPU {CPU_SECONDS[label]:.2f} s)"
        )
    seconds = best["ours, voxel queries (default)"]
    if "pyramid + pgeof level by level" in best:
        ratio = best["pyramid + pgeof level by level"] / seconds
        print(f"-> ours / pgeof level by level: {ratio:.2f}x")
    try:
        import jakteristics
    except ImportError:
        print("jakteristics not installed: skipped")
        return
    xyz = cloud.xyz - cloud.xyz.min(axis=0)
    tree = jakteristics.cKDTree(xyz)
    per_point_s = 0.0
    for size in config.voxel_sizes_m:
        radius = 2 * size
        queries = xyz if radius <= 0.4 else xyz[:: max(1, n // 4000)]
        started = time.perf_counter()
        jakteristics.compute_features(
            queries, search_radius=radius, kdtree=tree, num_threads=-1, feature_names=NINE
        )
        seconds_r = time.perf_counter() - started
        per_point_s += seconds_r / len(queries)
        print(f"  jakteristics r={radius:6.2f} m  {rate(len(queries), seconds_r)}")
    print(f"jakteristics, {config.n_levels} radii          {rate(1, per_point_s)}")
    print(f"-> ours / jakteristics: {per_point_s * n / seconds:.0f}x")


def training_set(data: Path, config: CovarianceConfig, scans: tuple[str, ...]):  # type: ignore[no-untyped-def]
    labelled = find_labelled_scans(data, names=[f"oakland_part2_{s}" for s in scans])
    return build_training_set(labelled, config=config)


def bench_forest(data: Path, repeat: int) -> None:
    config = CovarianceConfig()
    print(f"\n== forest: {config.forest}, {config.sampling.points_per_class} points/class")
    training = training_set(data, config, TRAIN)
    started = time.perf_counter()
    model = fit_model(training, config=config)
    print(
        f"fit {training.labels.size} rows: {time.perf_counter() - started:.1f} s "
        f"(features of the sample: {training.feature_time_s:.1f} s)"
    )
    cloud = read_ascii_points(data / "oakland_part2_aj.txt")
    rows = compute_multiscale_features(cloud, config=config.features).values
    forest = model.classifier.forest_
    forest.set_params(n_jobs=-1)
    compiled = model.classifier.compiled_
    proba = compiled.predict_proba(rows)
    expected = forest.predict_proba(rows)
    best = interleaved(
        repeat,
        {
            "ours": lambda: compiled.predict_proba(rows),
            "sklearn": lambda: forest.predict_proba(rows),
        },
    )
    ours, theirs = best["ours"], best["sklearn"]
    same = np.array_equal(proba.argmax(axis=1), expected.argmax(axis=1))
    print(f"{compiled.feature.size} nodes in {compiled.roots.size} trees")
    print(f"compiled forest          {len(rows) / ours / 1e3:8.0f} k rows/s")
    print(
        f"sklearn predict_proba    {len(rows) / theirs / 1e3:8.0f} k rows/s  "
        f"(same argmax: {same}, max |dp| {np.abs(proba - expected).max():.1e})"
    )


def bench_predict(data: Path, repeat: int, model_path: Path) -> None:
    from semantic3d.baselines.covariance.persistence import load_model, save_model

    config = CovarianceConfig()
    if not model_path.exists():
        save_model(fit_model(training_set(data, config, TRAIN), config=config), model_path)
    model = load_model(model_path)
    with tempfile.TemporaryDirectory() as tmp:
        scans = [data / "oakland_part2_aj.txt"]
        try:
            from semantic3d.datasets.simulator import simulate
        except ImportError:
            pass
        else:  # a dense static terrestrial scan, as in the benchmark
            result = simulate("street", out=Path(tmp) / "sim", n_points=1_000_000, seed=3)
            scans.append(result.scans[0].points_path)
        for scan in scans:
            print(f"\n== predict end to end (read, features, classify, write): {scan.name}")
            contenders: dict[str, Callable[[], Any]] = {}
            for label, limit in (("in memory", 10**9), ("tiled", 0)):
                prediction = dataclasses.replace(config.prediction, max_points_in_memory=limit)
                variant = dataclasses.replace(
                    model, config=dataclasses.replace(model.config, prediction=prediction)
                )
                contenders[f"{scan.name} {label}"] = lambda v=variant, s=scan: predict_scan(
                    v, s, out_path=Path(tmp) / "p.labels", overwrite=True
                )
            n_points = read_ascii_points(scan).n_points
            for label, seconds in interleaved(repeat, contenders).items():
                print(
                    f"{label:40s} {rate(n_points, seconds)}  ({seconds:.2f} s, "
                    f"CPU {CPU_SECONDS[label]:.2f} s)"
                )


def bench_memory(data: Path, model_path: Path) -> None:
    print("\n== peak RSS of tiled prediction vs scan size (Oakland aj copied side by side)")
    cloud = read_ascii_points(data / "oakland_part2_aj.txt")
    extent = cloud.xyz.max(axis=0) - cloud.xyz.min(axis=0) + 10.0
    with tempfile.TemporaryDirectory() as tmp:
        for copies in (1, 4, 16, 64):
            side = int(np.sqrt(copies))
            parts = [
                PointCloud.from_arrays(
                    cloud.xyz + np.array([extent[0] * (i % side), extent[1] * (i // side), 0.0]),
                    intensity=cloud.intensity,
                    rgb=cloud.rgb,
                )
                for i in range(copies)
            ]
            path = Path(tmp) / f"x{copies}.txt"
            write_ascii_points(path, parts)
            code = (
                f"import sys; sys.path.insert(0, {str(Path(__file__).resolve().parent)!r});"
                "import dataclasses;"
                "from _harness import peak_rss_mb;"
                "import semantic3d.features;"
                "from semantic3d.baselines.covariance.persistence import load_model;"
                "from semantic3d.baselines.covariance.predict import predict_scan;"
                f"m = load_model({str(model_path)!r});"
                "p = dataclasses.replace(m.config.prediction, max_points_in_memory=0,"
                " chunk_size=1 << 18);"
                "m = dataclasses.replace(m, config=dataclasses.replace(m.config, prediction=p));"
                f"r = predict_scan(m, {str(path)!r}, out_path={str(path) + '.labels'!r});"
                "print(r.n_points, r.runtime_s, int(peak_rss_mb() * 1024))"
            )
            out = subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True, check=True
            )
            n, seconds, rss_kib = out.stdout.split()
            print(
                f"{int(n):>9d} points: {float(seconds):6.1f} s "
                f"({int(n) / float(seconds) / 1e3:5.0f} k points/s), "
                f"peak RSS {int(rss_kib) / 1024:6.0f} MiB"
            )


def bench_density(model_path: Path, sizes: list[int]) -> None:
    from semantic3d.datasets.simulator import simulate

    print("\n== peak RSS of tiled prediction vs density (one simulated street station)")
    before: tuple[int, float] | None = None
    with tempfile.TemporaryDirectory() as tmp:
        for n_points in sizes:
            made = simulate("street", out=Path(tmp) / f"s{n_points}", n_points=n_points, seed=1)
            path = made.scans[0].points_path
            code = (
                f"import sys; sys.path.insert(0, {str(Path(__file__).resolve().parent)!r});"
                "from _harness import peak_rss_mb;"
                "from semantic3d.baselines.covariance.persistence import load_model;"
                "from semantic3d.baselines.covariance.predict import predict_scan;"
                f"m = load_model({str(model_path)!r});"
                f"r = predict_scan(m, {str(path)!r}, out_path={str(path) + '.predicted'!r},"
                f" workdir={tmp!r});"
                "print(r.n_points, r.runtime_s, int(peak_rss_mb() * 1024))"
            )
            out = subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True, check=True
            )
            n, seconds, rss_kib = out.stdout.split()
            rss_mib = int(rss_kib) / 1024
            growth = (
                ""
                if before is None
                else f", {(rss_mib - before[1]) / ((int(n) - before[0]) / 1e6):5.1f} MiB a "
                "million points more"
            )
            print(
                f"{int(n):>10d} points: {float(seconds):6.1f} s "
                f"({int(n) / float(seconds) / 1e3:5.0f} k points/s), "
                f"peak RSS {rss_mib:6.0f} MiB{growth}"
            )
            before = (int(n), rss_mib)
            shutil.rmtree(path.parent)


def bench_accuracy(data: Path) -> None:
    print("\n== accuracy on CMU Oakland (Munoz et al. 2009): train", TRAIN, "validate", VALIDATE)
    base = CovarianceConfig()
    variants = {
        "multi-scale, 9 levels from 0.025 m (default)": base.features,
        "multi-scale, per-point queries": dataclasses.replace(base.features, per_point=True),
        "single scale 0.1 m": FeatureConfig(base_voxel_size_m=0.1, n_levels=1),
        "single scale 0.4 m": FeatureConfig(base_voxel_size_m=0.4, n_levels=1),
    }
    results = {}
    for name, features in variants.items():
        config = dataclasses.replace(base, features=features)
        model = fit_model(training_set(data, config, TRAIN), config=config)
        matrix = ConfusionMatrix()
        with tempfile.TemporaryDirectory() as tmp:
            for scan in VALIDATE:
                stem = f"oakland_part2_{scan}"
                run = predict_scan(model, data / f"{stem}.txt", out_path=Path(tmp) / "p.labels")
                matrix.update(read_labels(data / f"{stem}.labels"), read_labels(run.labels_path))
        scores = matrix.compute_scores()
        results[name] = scores
        print(f"{name:45s} mIoU {scores.mean_iou:.3f}  OA {scores.overall_accuracy:.3f}")
    header = " ".join(f"{c.name[:10]:>10s}" for c in CLASSES)
    print(f"{'per-class IoU':45s} {header}")
    for name, scores in results.items():
        cells = " ".join("       n/a" if np.isnan(v) else f"{v:10.3f}" for v in scores.iou)
        print(f"{name:45s} {cells}")


PEER_RADII = (0.25, 0.5, 1.0, 2.0)


def peer_features(cloud: PointCloud, points: np.ndarray | None = None) -> np.ndarray:
    """jakteristics' 27 features at 4 radii + height above the scan's lowest point."""
    import jakteristics

    xyz = cloud.xyz - cloud.xyz.min(axis=0)
    queries = xyz if points is None else xyz[points]
    tree = jakteristics.cKDTree(xyz)
    parts = [
        jakteristics.compute_features(queries, search_radius=r, kdtree=tree, num_threads=-1)
        for r in PEER_RADII
    ]
    parts.append(queries[:, 2:3])
    return np.nan_to_num(np.hstack(parts).astype(np.float32))


def train_peer(data: Path, path: Path, points_per_class: int, seed: int = 0) -> None:
    import joblib
    from sklearn.ensemble import RandomForestClassifier

    rng = np.random.default_rng(seed)
    clouds = [
        read_ascii_points(
            data / f"oakland_part2_{s}.txt", labels_path=data / f"oakland_part2_{s}.labels"
        )
        for s in TRAIN
    ]
    labels = np.concatenate([c.labels for c in clouds])  # type: ignore[misc]
    owner = np.concatenate([np.full(c.n_points, i) for i, c in enumerate(clouds)])
    offset = np.concatenate([np.arange(c.n_points) for c in clouds])
    picks = []
    for value in np.unique(labels[labels > 0]):
        members = np.flatnonzero(labels == value)
        picks.append(rng.choice(members, size=min(points_per_class, members.size), replace=False))
    chosen = np.concatenate(picks)
    x = np.vstack(
        [
            peer_features(c, np.sort(offset[chosen[owner[chosen] == i]]))
            for i, c in enumerate(clouds)
        ]
    )
    y = np.concatenate(
        [c.labels[np.sort(offset[chosen[owner[chosen] == i]])] for i, c in enumerate(clouds)]  # type: ignore[index]
    )
    forest = RandomForestClassifier(n_estimators=50, max_depth=20, n_jobs=-1, random_state=seed)
    joblib.dump(forest.fit(x, y), path)


def run_child(kind: str, model_path: Path, scans: list[Path], out: Path) -> None:
    """One contender, end to end over ``scans``; prints points, wall s, CPU s, peak RSS KiB
    and the wall s of labelling alone (after start-up and loading the model). ``kind`` is
    ``ours-N`` (N scans at a time) or ``peer``."""
    started, cpu = time.perf_counter(), time.process_time()
    n_points = 0
    if kind.startswith("ours"):
        from semantic3d.baselines.common.submission import ScanToLabel
        from semantic3d.baselines.covariance.persistence import load_model
        from semantic3d.baselines.covariance.predict import predict_scans

        model = load_model(model_path)
        labelling = time.perf_counter()
        result = predict_scans(
            model,
            [ScanToLabel(p.stem, p, p.stem + ".labels") for p in scans],
            out,
            parallel_scans=int(kind.split("-")[1]),
        )
        n_points = result.n_points
    else:
        import joblib

        forest = joblib.load(model_path)
        forest.set_params(n_jobs=-1)
        out.mkdir(parents=True, exist_ok=True)
        labelling = time.perf_counter()
        for path in scans:
            cloud = read_ascii_points(path)
            labels = forest.predict(peer_features(cloud)).astype(np.uint8)
            np.savetxt(out / f"{path.stem}.labels", labels, fmt="%d")
            n_points += cloud.n_points
    finished = time.perf_counter()
    print(
        n_points,
        finished - started,
        time.process_time() - cpu,
        int(peak_rss_mb() * 1024),
        finished - labelling,
    )


CONTENDERS = {
    "ours, 2 scans at a time": "ours-2",
    "ours, 1 scan at a time": "ours-1",
    "jakteristics + sklearn": "peer",
}


def bench_peers(data: Path, repeat: int) -> None:
    print("\n== end to end on a folder (4 Oakland scans): ours vs jakteristics + scikit-learn")
    config = CovarianceConfig()
    scans = [data / f"oakland_part2_{s}.txt" for s in VALIDATE]
    with tempfile.TemporaryDirectory() as tmp:
        ours_model, peer_model = Path(tmp) / "ours.model", Path(tmp) / "peer.joblib"
        from semantic3d.baselines.covariance.persistence import save_model

        started = time.perf_counter()
        save_model(fit_model(training_set(data, config, TRAIN), config=config), ours_model)
        print(f"trained ours in {time.perf_counter() - started:.0f} s")
        started = time.perf_counter()
        train_peer(data, peer_model, config.sampling.points_per_class)
        print(f"trained jakteristics + scikit-learn in {time.perf_counter() - started:.0f} s")
        best: dict[str, tuple[float, float, float, int, float]] = {}
        for _ in range(repeat):
            for name, kind in CONTENDERS.items():
                model = peer_model if kind == "peer" else ours_model
                out = Path(tmp) / kind
                shutil.rmtree(out, ignore_errors=True)
                code = [sys.executable, __file__, "--child", kind, str(model), str(out)]
                line = subprocess.run(
                    [*code, *map(str, scans)], capture_output=True, text=True, check=True
                )
                n, wall, cpu, rss, loop = line.stdout.split()[-5:]
                if name not in best or float(wall) < best[name][0]:
                    best[name] = (float(wall), float(cpu), int(rss) / 1024, int(n), float(loop))
                if name not in SCORES:
                    matrix = ConfusionMatrix()
                    for scan in scans:
                        matrix.update(
                            read_labels(scan.with_suffix(".labels")),
                            read_labels(out / f"{scan.stem}.labels"),
                        )
                    SCORES[name] = matrix.compute_scores()
        for name, (wall, cpu, rss, n, loop) in best.items():
            scores = SCORES[name]
            print(
                f"{name:24s} {n / wall / 1e3:6.0f} k points/s ({wall:.1f} s, CPU {cpu:.1f} s); "
                f"labelling alone {n / loop / 1e3:6.0f} k points/s ({loop:.2f} s); "
                f"peak RSS {rss:5.0f} MiB, mIoU {scores.mean_iou:.3f}, OA "
                f"{scores.overall_accuracy:.3f}"
            )


SCORES: dict[str, Any] = {}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        kind, model, out, *scans = sys.argv[2:]
        run_child(kind, Path(model), [Path(s) for s in scans], Path(out))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--only", default="features,forest,predict,memory,accuracy,peers")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--density-points",
        type=int,
        nargs="+",
        default=[5_000_000, 10_000_000, 20_000_000, 40_000_000],
        help="points of the simulated station for --only density",
    )
    args = parser.parse_args()
    oakland = args.data / "oakland"
    if not oakland.is_dir():
        sys.exit(f"{oakland}: the real samples are needed (../shared/data)")
    only = set(args.only.split(","))
    print(
        "hardware:",
        describe_hardware().describe(),
        f"| OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}",
    )
    model_path = Path(tempfile.gettempdir()) / "s3d-bench-covariance.model"
    if "features" in only:
        bench_features(
            read_ascii_points(oakland / "oakland_part2_ac.txt"), "oakland_part2_ac", args.repeat
        )
        brighton = args.data / "odm-brighton" / "brighton_small.txt"
        if brighton.exists():
            bench_features(
                read_ascii_points(brighton), "brighton_small (photogrammetry)", args.repeat
            )
    if "forest" in only:
        bench_forest(oakland, args.repeat)
    if "predict" in only:
        bench_predict(oakland, args.repeat, model_path)
    if "memory" in only:
        if not model_path.exists():
            bench_predict(oakland, 1, model_path)
        bench_memory(oakland, model_path)
    if "density" in only:
        if not model_path.exists():
            bench_predict(oakland, 1, model_path)
        bench_density(model_path, args.density_points)
    if "accuracy" in only:
        bench_accuracy(oakland)
    if "peers" in only:
        bench_peers(oakland, args.repeat)
    print(f"\npeak RSS of this process: {peak_rss_mib():.0f} MiB")


if __name__ == "__main__":
    main()
