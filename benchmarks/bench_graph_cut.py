"""The covariance baseline's context step: alpha-expansion over a scan's k-NN voxel graph.

    python benchmarks/bench_graph_cut.py [--points 1500000] [--threads 1]

The graph is the one the context step cuts, for a whole scan that fits one tile: the
level-0 voxels of a simulated street scan (``simulate("street")``, one station, so the
density falls with range as in a real scan), each joined to its nearest voxels by the
feature table's lists, with unary costs from the class probabilities of a covariance
model trained on another simulated street scan. Default configuration (Potts weight,
neighbours, one sweep).

Contenders, each in its own process (wall time and peak RSS of that process):

1. ``semantic3d alpha_expansion``: the compiled Boykov-Kolmogorov cut and move loop.
2. ``PyMaxflow moves``: the same moves, each cut by PyMaxflow (the library a user would
   call: it wraps Kolmogorov's maxflow v3), its graph built with its array calls and the
   energy checked with ``potts_energy``: how the context step was first written.
3. ``arc pass per move (floor)``: one read of every arc's head, sister and residual and
   every node's terminal capacity per move, summed with numpy: memory traffic that any
   cut must at least spend, not a cut.
4. ``semantic3d, tiles cut whole``: the context step as ``predict`` ran it before
   (:func:`~semantic3d.baselines.covariance.context.label_rows_by_group` with
   ``max_group_rows=0``): each tile's edges taken from the neighbour lists and its graph
   cut alone, the tiles on ``--threads`` threads at once.
5. ``semantic3d, tiles cut in squares``: what ``predict`` runs by default: the same, a
   tile of more than ``[context] max_graph_nodes`` voxels cut in quadtree squares of at
   most that many. Not the same graph (no edge between two pieces): the share of labels
   that differ from the tiles' is printed.

The first two cuts give the same labels (checked here, and in the tests). Rates count
graph nodes times moves per second.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import OUT, Measurement, emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()
N_CLASSES = 8


def _graph(n_points: int, folder: Path) -> Path:
    """The benchmark's graph (``.npz``: unary costs and edges), as the context step builds
    it: a covariance model (default configuration) trained on one simulated street scan
    gives the class probabilities of another's voxels, joined by their feature table's
    nearest-neighbour lists."""
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.context import graph_edges, unary_costs
    from semantic3d.baselines.covariance.model import point_cells, point_tiles
    from semantic3d.baselines.covariance.training import (
        build_training_set,
        find_labelled_scans,
        fit_model,
    )
    from semantic3d.datasets.simulator import simulate
    from semantic3d.features import compute_multiscale_features
    from semantic3d.features.pyramid import grid_origin
    from semantic3d.io.ascii import read_ascii_points

    config = CovarianceConfig()
    train = simulate("street", out=folder / "train", n_points=n_points // 3, seed=4).scans[0]
    scans = find_labelled_scans(train.points_path.parent, names=[train.points_path.stem])
    model = fit_model(build_training_set(scans, config=config), config=config)
    scan = simulate("street", out=folder / "test", n_points=n_points, seed=1).scans[0]
    table = compute_multiscale_features(read_ascii_points(scan.points_path), config=config.features)
    proba = model.classifier.predict_proba(table.values)
    n_neighbours = config.context.n_neighbours
    edges = graph_edges(table.n_rows, None, n_neighbours=n_neighbours, neighbours=table.neighbours)
    points = read_ascii_points(scan.points_path)
    origin = grid_origin(points.xyz[0], coarsest_voxel_size_m=config.features.coarsest_voxel_size_m)
    row_tile = np.zeros(table.n_rows, np.int64)
    row_tile[table.point_row] = point_tiles(points.xyz, origin=origin, config=config)
    row_cell = np.zeros(table.n_rows, np.uint16)
    row_cell[table.point_row] = point_cells(points.xyz, origin=origin, config=config)
    path = folder / "graph.npz"
    np.savez(
        path,
        unary=unary_costs(proba),
        edges=edges,
        weight=config.context.potts_weight,
        proba=proba,
        lists=table.neighbours[:, : n_neighbours + 1],
        row_tile=row_tile,
        row_cell=row_cell,
    )
    return path


def _load(path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    with np.load(path) as data:
        unary, edges = np.ascontiguousarray(data["unary"]), np.ascontiguousarray(data["edges"])
        return unary, edges, float(data["weight"])


_PIECES: dict[str, np.ndarray] = {}  # the squares contender's inputs, loaded in its child


def _warm_up() -> None:
    """Load the compiled kernels and libraries before the clock starts."""
    sys.path.insert(0, str(HERE.parents[1]))
    import tests.baselines.covariance.test_graph_cut  # noqa: F401  (PyMaxflow's contender)

    from semantic3d.baselines.covariance.context import alpha_expansion, potts_energy

    unary = np.random.default_rng(0).random((64, N_CLASSES))
    edges = np.column_stack([np.arange(63), np.arange(1, 64)])
    alpha_expansion(unary, edges, weight=1.0)
    potts_energy(unary, edges, unary.argmin(axis=1), weight=1.0)


def _compiled(unary: np.ndarray, edges: np.ndarray, weight: float) -> np.ndarray:
    from semantic3d.baselines.covariance.context import alpha_expansion

    return alpha_expansion(unary, edges, weight=weight, max_sweeps=1)


def _pymaxflow(unary: np.ndarray, edges: np.ndarray, weight: float) -> np.ndarray:
    # the reference the tests check the compiled cut against, moves cut by PyMaxflow
    from tests.baselines.covariance.test_graph_cut import pymaxflow_expansion

    return pymaxflow_expansion(unary, edges, weight, 1)


def _floor(unary: np.ndarray, edges: np.ndarray, weight: float) -> np.ndarray:
    n, n_labels = unary.shape
    arcs = 2 * edges.shape[0]
    head, sister = np.arange(arcs, dtype=np.int32), np.arange(arcs, dtype=np.int32)
    residual, terminal = np.ones(arcs), np.ones(n)
    total = 0.0
    for _ in range(n_labels):
        total += float(head.sum() + sister.sum()) + float(residual.sum() + terminal.sum())
    return np.array([total])


def _tiles(unary: np.ndarray, edges: np.ndarray, weight: float) -> np.ndarray:
    return _by_group(weight, 0)


def _squares(unary: np.ndarray, edges: np.ndarray, weight: float) -> np.ndarray:
    from semantic3d.baselines.covariance.config import ContextConfig

    return _by_group(weight, ContextConfig().max_graph_nodes)


def _by_group(weight: float, max_group_rows: int) -> np.ndarray:
    from semantic3d.baselines.covariance.config import ContextConfig
    from semantic3d.baselines.covariance.context import label_rows_by_group

    context = ContextConfig()
    return label_rows_by_group(
        _PIECES["proba"],
        None,
        _PIECES["row_tile"],
        potts_weight=weight,
        n_neighbours=context.n_neighbours,
        max_sweeps=1,
        neighbours=_PIECES["lists"],
        row_cell=_PIECES["row_cell"],
        max_group_rows=max_group_rows,
    )


CONTENDERS = {
    "semantic3d alpha_expansion": _compiled,
    "PyMaxflow moves": _pymaxflow,
    "arc pass per move (floor)": _floor,
    "semantic3d, tiles cut whole": _tiles,
    "semantic3d, tiles cut in squares": _squares,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=1_500_000)
    parser.add_argument("--threads", type=int, default=1, help="the compiled cut's thread budget")
    parser.add_argument("--child", nargs=3, metavar=("NAME", "GRAPH", "OUT"))
    args = parser.parse_args()
    if args.child:
        from semantic3d.core.threads import set_thread_limit

        set_thread_limit(args.threads)
        name, graph, out = args.child
        unary, edges, weight = _load(Path(graph))
        if name.startswith("semantic3d, tiles"):
            with np.load(graph) as data:
                _PIECES.update(
                    {key: data[key] for key in ("proba", "lists", "row_tile", "row_cell")}
                )
        _warm_up()
        result: list[np.ndarray] = []

        def run() -> int:
            result.append(CONTENDERS[name](unary, edges, weight))
            return unary.shape[0] * unary.shape[1]  # node-moves: one move per class

        measured = measure_here(name, run)
        np.save(out, result[0])
        emit(measured)
        return
    with tempfile.TemporaryDirectory(prefix="s3d-bench-cut-") as tmp:
        folder = Path(tmp)
        graph = _graph(args.points, folder)
        unary, edges, _ = _load(graph)
        rows: list[Measurement] = []
        labels = {}
        for name in CONTENDERS:
            out = folder / f"{len(rows)}.npy"
            rows.append(
                measure_in_child(HERE, name, str(graph), str(out), "--threads", str(args.threads))
            )
            labels[name] = np.load(out)
        whole = labels["semantic3d alpha_expansion"]
        same = bool(np.array_equal(whole, labels["PyMaxflow moves"]))
        changed = float(
            np.mean(
                labels["semantic3d, tiles cut in squares"] != labels["semantic3d, tiles cut whole"]
            )
        )
    title = (
        f"alpha-expansion, one sweep: {unary.shape[0]:,} voxels, {edges.shape[0]:,} edges, "
        f"{unary.shape[1]} classes ({args.points:,} simulated points), {args.threads} "
        f"thread(s); same labels: {same}; tiles cut in squares: {100 * changed:.2f} % of "
        "the tiles' labels differ"
    )
    print(table(title, "node-moves", rows, baseline="PyMaxflow moves"))
    OUT.mkdir(exist_ok=True)
    record = {
        "title": title,
        "same_labels": same,
        "squares_changed_share": changed,
        "rows": [
            {"name": r.name, "rate": r.rate, "seconds": r.seconds, "peak_rss_mb": r.peak_rss_mb}
            for r in rows
        ],
    }
    (OUT / "bench_graph_cut.json").write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
