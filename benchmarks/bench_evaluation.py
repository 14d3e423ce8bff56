"""Throughput and peak memory of evaluation, in one run, against what a user would pick instead.

    python benchmarks/bench_evaluation.py [--labels 100000000] [--agreement-points 2000000]
                                          [--only evaluation|update|agreement]

1. End-to-end evaluation (parse ground truth + prediction, accumulate the matrix) of one
   scan of ``--labels`` single-digit lines, generated once under benchmarks/out/:
   ``evaluate_submission`` on a folder and on a zip, against the io reader paired with the
   accumulator, pandas + sklearn, polars + numpy and ``np.loadtxt`` (the original Python 2
   evaluator's approach; on a 2 M-line prefix, it is too slow for more).
2. ``ConfusionMatrix.update`` against ``sklearn.metrics.confusion_matrix`` and
   ``np.bincount`` on in-memory uint8 arrays.
3. The label-agreement check on two overlapping scans of the simulated ``street`` scene
   (two stations, ``--agreement-points`` each, as ``semantic3d simulate`` writes them):
   from the ASCII files (what ``semantic3d agreement`` does, parsing included) and in
   memory, against one untiled ``cKDTree`` per direction (the textbook approach); then
   the same on volumetric noise (points scattered uniformly through walls and tree
   crowns: no structure, the worst case for the occupancy filter).

Each contender runs in its own process (benchmarks/_harness.py), so peak RSS is its own.
Targets: evaluation >= 150 M labels/s, update >= 10x sklearn, agreement >= 1 M points/s.
"""

from __future__ import annotations

import argparse
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from semantic3d.core import PointCloud

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import OUT, Measurement, emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()
LOADTXT_LINES = 2_000_000
UPDATE_PAIRS = 20_000_000
CHUNK = 1 << 22


# ----------------------------------------------------------------------------- data


def _label_chunks(n: int, *, seed: int, prediction_of: int | None = None) -> Iterator[np.ndarray]:
    """Ground truth in runs of one class (as scans are), or a 20 %-noisy prediction of it."""
    rng = np.random.default_rng(seed)
    truth_rng = np.random.default_rng(prediction_of) if prediction_of is not None else None
    for start in range(0, n, CHUNK):
        size = min(CHUNK, n - start)
        source = truth_rng if truth_rng is not None else rng
        runs = source.integers(0, 9, size // 64 + 1).astype(np.uint8)
        truth = np.repeat(runs, 64)[:size]
        if prediction_of is None:
            yield truth
            continue
        pred = np.where(truth == 0, 1, truth).astype(np.uint8)
        flip = rng.random(size) < 0.2
        pred[flip] = rng.integers(1, 9, int(flip.sum()), dtype=np.uint8)
        yield pred


def make_submission(n: int) -> tuple[Path, Path, Path]:
    """``(gt_dir, pred_dir, pred_zip)`` for one scan of ``n`` lines, written once."""
    from semantic3d.io import write_labels

    root = OUT / f"evaluation_{n}"
    gt_dir, pred_dir, pred_zip = root / "gt", root / "pred", root / "pred.zip"
    if pred_zip.exists():
        return gt_dir, pred_dir, pred_zip
    gt_dir.mkdir(parents=True, exist_ok=True)
    pred_dir.mkdir(parents=True, exist_ok=True)
    write_labels(gt_dir / "scan.labels", _label_chunks(n, seed=1))
    write_labels(pred_dir / "scan.labels", _label_chunks(n, seed=2, prediction_of=1))
    tmp = root / "pred.zip.tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        archive.write(pred_dir / "scan.labels", "scan.labels")
    tmp.rename(pred_zip)
    return gt_dir, pred_dir, pred_zip


def _overlapping_scans(n_points: int) -> tuple[PointCloud, PointCloud]:
    """Two scans of one street (ground, two facades, trees) seen from two stations."""

    def scan(seed: int, offset: float) -> PointCloud:
        rng = np.random.default_rng(seed)
        n = n_points
        kind = rng.integers(0, 4, n)
        x = rng.uniform(offset, offset + 60.0, n)
        y = rng.uniform(0.0, 20.0, n)
        z = np.zeros(n)
        wall = kind == 1
        y[wall] = np.where(rng.random(int(wall.sum())) < 0.5, 0.0, 20.0)
        z[wall] = rng.uniform(0.0, 15.0, int(wall.sum()))
        tree = kind == 2
        z[tree] = rng.uniform(3.0, 8.0, int(tree.sum()))
        labels = np.select([kind == 0, wall, tree], [1, 5, 3], default=4).astype(np.uint8)
        z[kind == 3] = rng.uniform(0.0, 1.0, int((kind == 3).sum()))
        xyz = np.column_stack([x, y, z]) + rng.normal(0.0, 0.003, (n, 3))
        return PointCloud.from_arrays(xyz, labels=labels)

    return scan(1, 0.0), scan(2, 30.0)


def make_simulated_scans(n_points: int) -> tuple[Path, Path, Path, Path]:
    """Two overlapping stations of the simulated street, written once."""
    from semantic3d.datasets.simulator import simulate

    root = OUT / f"agreement_street_{n_points}"
    names = ("street_station1.txt", "street_station1.labels")
    names += ("street_station2.txt", "street_station2.labels")
    files = tuple(root / name for name in names)
    if not all(f.exists() for f in files):
        simulate("street", out=root, n_points=n_points, stations=2, seed=1)
    a_txt, a_labels, b_txt, b_labels = files
    return a_txt, a_labels, b_txt, b_labels


def make_agreement_files(n_points: int) -> tuple[Path, Path, Path, Path]:
    from semantic3d.io import write_ascii_points

    root = OUT / f"agreement_{n_points}"
    a_txt, a_labels, b_txt, b_labels = (
        root / n for n in ("a.txt", "a.labels", "b.txt", "b.labels")
    )
    if not all(f.exists() for f in (a_txt, a_labels, b_txt, b_labels)):
        root.mkdir(parents=True, exist_ok=True)
        a, b = _overlapping_scans(n_points)
        write_ascii_points(a_txt, [a], labels_path=a_labels)
        write_ascii_points(b_txt, [b], labels_path=b_labels)
    return a_txt, a_labels, b_txt, b_labels


# ----------------------------------------------------------------------------- contenders


def _warm_up() -> None:
    """Load the compiled kernels (numba's on-disk cache) before the clock starts: a file
    longer than the texts parsed with numpy (1 MiB), so the kernels run once."""
    from semantic3d.evaluation import custom_challenge, evaluate_submission
    from semantic3d.io import read_labels

    warm = OUT / "warm_evaluation"
    warm.mkdir(parents=True, exist_ok=True)
    (warm / "w.labels").write_text("1\n2\n" * 400_000)
    evaluate_submission(warm, challenge=custom_challenge(warm))
    read_labels(warm / "w.labels")


def _evaluation(name: str, n: int) -> Measurement:
    gt_dir, pred_dir, pred_zip = make_submission(n)
    gt, pred = gt_dir / "scan.labels", pred_dir / "scan.labels"
    if name.startswith("semantic3d.evaluate_submission"):
        from semantic3d.evaluation import custom_challenge, evaluate_submission

        _warm_up()
        submission = pred_zip if "zip" in name else pred_dir
        challenge = custom_challenge(gt_dir)

        def evaluate() -> int:
            evaluate_submission(submission, challenge=challenge)
            return n

        return measure_here(name, evaluate)
    if name == "io.iter_labels x2 + ConfusionMatrix":
        from semantic3d.io import iter_labels
        from semantic3d.metrics import ConfusionMatrix

        _warm_up()

        def paired() -> int:
            cm = ConfusionMatrix()
            for t, p in zip(
                iter_labels(gt, chunk_size=CHUNK), iter_labels(pred, chunk_size=CHUNK), strict=True
            ):
                cm.update(t, p)
            return n

        return measure_here(name, paired)
    if name == "pandas.read_csv + sklearn":
        import pandas as pd
        from sklearn.metrics import confusion_matrix

        def pandas_sklearn() -> int:
            total = np.zeros((8, 8), np.int64)
            options = {"header": None, "engine": "c", "dtype": np.uint8, "chunksize": 1 << 23}
            for t, p in zip(pd.read_csv(gt, **options), pd.read_csv(pred, **options), strict=True):
                t_values, p_values = t[0].to_numpy(), p[0].to_numpy()
                keep = t_values > 0
                total += confusion_matrix(t_values[keep], p_values[keep], labels=np.arange(1, 9))
            return n

        return measure_here(name, pandas_sklearn)
    if name == "polars.read_csv + np.bincount":
        import polars as pl

        def polars_numpy() -> int:
            t = pl.read_csv(
                gt, has_header=False, new_columns=["v"], schema_overrides={"v": pl.UInt8}
            )
            p = pl.read_csv(
                pred, has_header=False, new_columns=["v"], schema_overrides={"v": pl.UInt8}
            )
            t_values, p_values = t["v"].to_numpy(), p["v"].to_numpy()
            keep = t_values > 0
            codes = t_values[keep].astype(np.int64) * 9 + p_values[keep]
            np.bincount(codes, minlength=81).reshape(9, 9)[1:, 1:]
            return n

        return measure_here(name, polars_numpy)
    if name == "np.loadtxt + sklearn (2 M lines)":
        from itertools import islice

        from sklearn.metrics import confusion_matrix

        def loadtxt() -> int:
            with gt.open() as g, pred.open() as q:
                t = np.loadtxt(islice(g, LOADTXT_LINES), dtype=np.int64)
                p = np.loadtxt(islice(q, LOADTXT_LINES), dtype=np.int64)
            keep = t > 0
            confusion_matrix(t[keep], p[keep], labels=np.arange(1, 9))
            return LOADTXT_LINES

        return measure_here(name, loadtxt)
    raise SystemExit(f"unknown contender {name}")


def _update(name: str) -> Measurement:
    rng = np.random.default_rng(0)
    truth = np.repeat(rng.integers(0, 9, UPDATE_PAIRS // 64, dtype=np.uint8), 64)
    pred = np.where(rng.random(truth.size) < 0.8, np.maximum(truth, 1), 3).astype(np.uint8)
    if name == "ConfusionMatrix.update":
        from semantic3d.metrics import ConfusionMatrix

        cm = ConfusionMatrix()
        cm.update(truth[:100], pred[:100])  # compile / load the kernel

        def update() -> int:
            for start in range(0, truth.size, 1 << 20):
                cm.update(truth[start : start + (1 << 20)], pred[start : start + (1 << 20)])
            return int(truth.size)

        return measure_here(name, update)
    if name == "sklearn confusion_matrix":
        from sklearn.metrics import confusion_matrix

        def sklearn_update() -> int:
            for start in range(0, truth.size, 1 << 20):
                t, p = truth[start : start + (1 << 20)], pred[start : start + (1 << 20)]
                confusion_matrix(t, p, labels=np.arange(9))
            return int(truth.size)

        return measure_here(name, sklearn_update)
    if name == "np.bincount(t * 9 + p)":

        def bincount() -> int:
            for start in range(0, truth.size, 1 << 20):
                t, p = truth[start : start + (1 << 20)], pred[start : start + (1 << 20)]
                np.bincount(t.astype(np.intp) * 9 + p, minlength=81)
            return int(truth.size)

        return measure_here(name, bincount)
    raise SystemExit(f"unknown contender {name}")


def _agreement(name: str, scans: str, n_points: int) -> Measurement:
    from scipy.spatial import cKDTree  # imported before the clock starts

    from semantic3d.evaluation.agreement import compute_label_agreement
    from semantic3d.io import read_points

    small_a, small_b = _overlapping_scans(1_000)
    compute_label_agreement([small_a], [small_b])  # warm the kernels
    files = make_simulated_scans(n_points) if scans == "street" else make_agreement_files(n_points)
    if name == "compute_label_agreement_files (ASCII)":
        from semantic3d.evaluation.agreement import compute_label_agreement_files

        total = sum(1 for _ in files[1].open("rb")) + sum(1 for _ in files[3].open("rb"))
        return measure_here(name, lambda: (compute_label_agreement_files(*files), total)[1])
    a = read_points(files[0], labels_path=files[1])
    b = read_points(files[2], labels_path=files[3])
    total = a.n_points + b.n_points
    if name == "compute_label_agreement (in memory)":
        return measure_here(name, lambda: (compute_label_agreement([a], [b]), total)[1])
    if name == "cKDTree untiled":
        from semantic3d.metrics import ConfusionMatrix

        def untiled() -> int:
            for receiver, source in ((b, a), (a, b)):
                labels_r, labels_s = np.asarray(receiver.labels), np.asarray(source.labels)
                keep_r = ~np.isin(labels_r, (0, 7))
                keep_s = ~np.isin(labels_s, (0, 7))
                tree = cKDTree(source.xyz[keep_s])
                distance, index = tree.query(
                    receiver.xyz[keep_r],
                    k=1,
                    distance_upper_bound=0.05,
                    workers=-1,
                )
                matched = np.isfinite(distance)
                cm = ConfusionMatrix()
                cm.update(
                    labels_r[keep_r][matched],
                    labels_s[keep_s][index[matched]],
                )
            return total

        return measure_here(name, untiled)
    raise SystemExit(f"unknown contender {name}")


def run_child(name: str, argument: str) -> Measurement:
    group, _, contender = name.partition(":")
    if group == "evaluation":
        return _evaluation(contender, int(argument))
    if group == "update":
        return _update(contender)
    if group == "agreement":
        scans, _, n_points = argument.partition(":")
        return _agreement(contender, scans, int(n_points))
    raise SystemExit(f"unknown group {group}")


# ----------------------------------------------------------------------------- main


def _read_through(paths: list[Path]) -> None:
    """Warm the page cache so every contender reads from memory."""
    for path in paths:
        with path.open("rb") as stream:
            while stream.read(64 << 20):
                pass


def _evaluation_section(n: int, *, skip_slow: bool) -> str:
    gt_dir, pred_dir, pred_zip = make_submission(n)
    _read_through([gt_dir / "scan.labels", pred_dir / "scan.labels", pred_zip])
    measure_in_child(HERE, "evaluation:semantic3d.evaluate_submission (folder)", "1000")
    size_mb = (gt_dir / "scan.labels").stat().st_size / 1e6
    print(
        f"one scan of {n:,} labels: ground truth {size_mb:.0f} MB, prediction zip "
        f"{pred_zip.stat().st_size / 1e6:.1f} MB"
    )
    contenders = [
        "semantic3d.evaluate_submission (folder)",
        "semantic3d.evaluate_submission (zip)",
        "io.iter_labels x2 + ConfusionMatrix",
        "polars.read_csv + np.bincount",
    ]
    if not skip_slow:
        contenders += ["pandas.read_csv + sklearn", "np.loadtxt + sklearn (2 M lines)"]
    rows = [measure_in_child(HERE, f"evaluation:{c}", str(n)) for c in contenders]
    print(
        table(
            "end-to-end evaluation (parse gt + pred, accumulate)",
            "labels",
            rows,
            "polars.read_csv + np.bincount",
        )
    )
    print()
    return f"evaluation {rows[0].rate / 1e6:.0f} M labels/s (>= 150)"


def _update_section() -> str:
    rows = [
        measure_in_child(HERE, f"update:{c}", "0")
        for c in ("ConfusionMatrix.update", "sklearn confusion_matrix", "np.bincount(t * 9 + p)")
    ]
    print(
        table(
            f"accumulate {UPDATE_PAIRS:,} in-memory uint8 pairs (1 Mi chunks)",
            "pairs",
            rows,
            "sklearn confusion_matrix",
        )
    )
    print()
    return f"update {rows[0].rate / rows[1].rate:.0f}x sklearn (>= 10)"


def _agreement_section(m: int) -> str:
    make_simulated_scans(m)
    make_agreement_files(m)
    rates = {}
    for scans, title in (
        ("street", f"label agreement, simulated street, 2 stations x {m:,} points, 5 cm"),
        ("noise", f"label agreement, volumetric noise, 2 x {m:,} points, 5 cm"),
    ):
        rows = [
            measure_in_child(HERE, f"agreement:{c}", f"{scans}:{m}")
            for c in (
                "compute_label_agreement_files (ASCII)",
                "compute_label_agreement (in memory)",
                "cKDTree untiled",
            )
        ]
        print(table(title, "points", rows, "cKDTree untiled"))
        print()
        rates[scans] = rows[0].rate
    return (
        f"agreement from ASCII files {rates['street'] / 1e6:.2f} M points/s "
        f"(volumetric noise {rates['noise'] / 1e6:.2f}) (>= 1)"
    )


SECTIONS = ("evaluation", "update", "agreement")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--labels", type=int, default=100_000_000)
    parser.add_argument("--agreement-points", type=int, default=2_000_000)
    parser.add_argument("--child", nargs=2, metavar=("NAME", "ARG"))
    parser.add_argument("--skip-slow", action="store_true", help="Skip pandas and np.loadtxt.")
    parser.add_argument(
        "--only", choices=SECTIONS, action="append", help="Run only these sections."
    )
    args = parser.parse_args()
    if args.child:
        emit(run_child(*args.child))
        return
    sections = args.only or SECTIONS
    targets = []
    if "evaluation" in sections:
        targets.append(_evaluation_section(args.labels, skip_slow=args.skip_slow))
    if "update" in sections:
        targets.append(_update_section())
    if "agreement" in sections:
        targets.append(_agreement_section(args.agreement_points))
    print("targets: " + ", ".join(targets))


if __name__ == "__main__":
    main()
