"""The labelling app on simulated scans: level of detail, first frame, server operations, RSS,
and a scripted labelling run through the HTTP API.

    python benchmarks/bench_labelling.py [--points 1000000 10000000] [--script-points 1000000]

Per scan size (a simulated ``village`` scan, one station; simulation and cache built
beforehand and timed separately), in a fresh process each:

1. ``lod build``: :func:`semantic3d.labelling.lod.build_lod` from the cache (four streaming
   passes); beside it the cache's spatial tile store (``open_cache_tiles``), the other
   one-off index a scan gets, as a reference for a streaming rewrite of the same points.
2. ``first frame``: open the session, ``GET /api/scan`` and the nodes the page loads first
   (breadth first up to 300 000 points), through FastAPI's TestClient: a proxy for the time
   to the first frame (the browser's own drawing is not included).
3. ``polygon split`` / ``plane fit``: server time over the full working set (every point):
   a top-view square around the scanner, then a ground plane through three points near it.
   Beside them, the library a user would pick instead on the same points: matplotlib's
   ``Path.contains_points`` (on the projected points, projection included) and
   scikit-learn's ``RANSACRegressor`` (on the fit's candidate points).
4. peak RSS of the process.

Then the scripted labelling run (``--script-points``): buildings with the 3D workflow (per
building: a top-view crop, then plane fits through three picked points, each followed by
assign) and the ground with the 2D workflow (8 m top-view squares, then a front-view
polygon below the local ground + 0.4 m). The script's "eyes" are the simulator's truth
(where a user would click: on a building, on the ground); its hands are the HTTP API the
page uses. It reports the IoU of buildings and of ground (man-made + natural terrain)
against the truth, and the number of operations.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import OUT

HERE = Path(__file__).resolve()
DATA = OUT / "labelling"
FIRST_FRAME_POINTS = 300_000


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _client(app: Any) -> Any:
    """A TestClient speaking to the app as its page does (loopback Host, the secret)."""
    from fastapi.testclient import TestClient

    return TestClient(
        app, base_url="http://127.0.0.1:8765", headers={"X-Semantic3D-Token": app.state.secret}
    )


def prepare(n_points: int) -> dict[str, Any]:
    """Simulate the scan and build its cache once (timed, reused on later runs)."""
    from semantic3d.datasets.simulator import simulate
    from semantic3d.io import build_cache

    folder = DATA / f"{n_points}"
    record = folder / "prepared.json"
    if record.is_file():
        return json.loads(record.read_text())
    start = time.perf_counter()
    result = simulate("village", out=folder, n_points=n_points, seed=5)
    simulate_s = time.perf_counter() - start
    scan = result.scans[0]
    start = time.perf_counter()
    build_cache(scan.points_path, folder / "scan.cache")
    cache_s = time.perf_counter() - start
    data = {
        "n_points": scan.n_points,
        "cache": str(folder / "scan.cache"),
        "truth": str(scan.labels_path),
        "station_m": list(scan.station.position),
        "simulate_s": simulate_s,
        "cache_s": cache_s,
    }
    record.write_text(json.dumps(data, indent=2))
    return data


def _top_view(centre: np.ndarray, half_m: float) -> np.ndarray:
    """Row-major orthographic top view: x, y in centre ± half_m fill NDC -1..1."""
    return np.array(
        [
            [1 / half_m, 0, 0, -centre[0] / half_m],
            [0, 1 / half_m, 0, -centre[1] / half_m],
            [0, 0, -1e-4, 0],
            [0, 0, 0, 1],
        ]
    )


def _front_view(centre: np.ndarray, half_m: float) -> np.ndarray:
    """Row-major orthographic front view (looking along +y): x across, z up."""
    return np.array(
        [
            [1 / half_m, 0, 0, -centre[0] / half_m],
            [0, 0, 1 / half_m, -centre[2] / half_m],
            [0, 1e-4, 0, 0],
            [0, 0, 0, 1],
        ]
    )


SQUARE = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]


def child_measure(prepared: dict[str, Any]) -> dict[str, Any]:
    """Everything of one scan size, in this (fresh) process."""
    from semantic3d.labelling.app import create_label_app
    from semantic3d.labelling.lod import LOD_FOLDER, build_lod
    from semantic3d.labelling.opening import open_label_session
    from semantic3d.spatial import open_cache_tiles

    cache = Path(prepared["cache"])
    out: dict[str, Any] = {"n_points": prepared["n_points"]}
    cpu = time.process_time()
    start = time.perf_counter()
    lod = build_lod(cache, cache / LOD_FOLDER)
    out["lod_build_s"] = time.perf_counter() - start
    out["lod_build_cpu_s"] = time.process_time() - cpu
    out["lod_nodes"] = len(lod.nodes)
    out["rss_after_lod_mb"] = _rss_mb()

    with tempfile.TemporaryDirectory() as scratch:
        start = time.perf_counter()
        session = open_label_session(
            cache, labels_path=Path(scratch) / "bench.labels", cache_dir=DATA / "user-cache"
        )
        client = _client(create_label_app(session, port=8765))
        scan = client.get("/api/scan").json()
        loaded = 0
        for node in scan["hierarchy"]["nodes"]:  # breadth first, as the page loads them
            if loaded + node["count"] > FIRST_FRAME_POINTS and loaded:
                break
            client.get(f"/api/nodes/{node['id']}")
            client.get(f"/api/nodes/{node['id']}/state")
            loaded += node["count"]
        out["first_frame_s"] = time.perf_counter() - start
        out["first_frame_points"] = loaded

        origin = np.asarray(scan["hierarchy"]["origin"])
        station = np.asarray(prepared["station_m"]) - origin
        matrix = _top_view(station, 30.0)
        body = {"view_projection": matrix.reshape(-1).tolist(), "polygon": SQUARE}
        for attempt in ("split_first", "split"):  # the first loads the compiled kernel
            cpu = time.process_time()
            start = time.perf_counter()
            split = client.post("/api/split", json=body).json()
            out[f"{attempt}_s"] = time.perf_counter() - start
            out[f"{attempt}_cpu_s"] = time.process_time() - cpu
            if attempt == "split_first":
                client.post("/api/undo")
        out["split_kept"] = split["result"]["n_working"]
        client.post("/api/undo")  # the fit runs over the full working set too

        ground = station - (0, 0, prepared["station_m"][2])
        seeds = [(ground + d).tolist() for d in ((3, 0, 0), (-2, 2.5, 0), (0, -3, 0))]
        cpu = time.process_time()
        start = time.perf_counter()
        fit = client.post(
            "/api/fit", json={"kind": "plane", "seeds": seeds, "tolerance_m": 0.1}
        ).json()
        out["fit_s"] = time.perf_counter() - start
        out["fit_cpu_s"] = time.process_time() - cpu
        out["fit_inliers"] = fit["result"]["n_inliers"]
        out["rss_peak_mb"] = _rss_mb()  # LOD build and the session's operations
        session.close()
    start = time.perf_counter()
    open_cache_tiles(cache)
    out["tile_store_build_s"] = time.perf_counter() - start

    # The libraries a user would pick instead, on the same points (whole scan in memory).
    from matplotlib.path import Path as MplPath
    from sklearn.linear_model import RANSACRegressor

    xyz = np.load(cache / "xyz.npy", mmap_mode="r")
    start = time.perf_counter()
    kept = 0
    for a in range(0, len(xyz), 1 << 21):
        block = np.asarray(xyz[a : a + (1 << 21)]) - origin
        ndc = (block @ matrix[:2, :3].T + matrix[:2, 3]) / 1.0
        kept += int(MplPath(np.array(SQUARE)).contains_points(ndc).sum())
    out["split_matplotlib_s"] = time.perf_counter() - start
    out["split_matplotlib_kept"] = kept
    near = []
    centre = np.mean(seeds, axis=0)
    for a in range(0, len(xyz), 1 << 21):
        block = np.asarray(xyz[a : a + (1 << 21)]) - origin
        near.append(block[np.linalg.norm(block - centre, axis=1) <= 4.5])
    candidates = np.concatenate(near)
    start = time.perf_counter()
    ransac = RANSACRegressor(residual_threshold=0.1, random_state=0, max_trials=256)
    ransac.fit(candidates[:, :2], candidates[:, 2])
    inliers = np.zeros(len(xyz), bool)
    coef, intercept = ransac.estimator_.coef_, ransac.estimator_.intercept_
    for a in range(0, len(xyz), 1 << 21):
        block = np.asarray(xyz[a : a + (1 << 21)]) - origin
        residual = np.abs(block[:, 2] - block[:, :2] @ coef - intercept)
        inliers[a : a + len(block)] = residual <= 0.1
    out["fit_sklearn_s"] = time.perf_counter() - start
    out["fit_sklearn_candidates"] = len(candidates)
    return out


def scripted_run(prepared: dict[str, Any]) -> dict[str, Any]:
    """Label buildings (3D workflow) and ground (2D workflow) through the HTTP API."""
    from scipy import ndimage

    from semantic3d.io import read_labels
    from semantic3d.labelling.app import create_label_app
    from semantic3d.labelling.opening import open_label_session

    cache = Path(prepared["cache"])
    truth = read_labels(prepared["truth"])
    xyz = np.load(cache / "xyz.npy")
    rng = np.random.default_rng(0)
    operations = 0
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        session = open_label_session(
            cache, labels_path=Path(scratch) / "script.labels", cache_dir=DATA / "user-cache"
        )
        client = _client(create_label_app(session, port=8765))
        origin = np.asarray(client.get("/api/scan").json()["hierarchy"]["origin"])
        local = xyz - origin

        def post(path: str, body: dict[str, Any]) -> dict[str, Any]:
            nonlocal operations
            operations += 1
            answer = client.post(path, json=body)
            if answer.status_code != 200:
                raise RuntimeError(f"{path}: {answer.text}")
            return answer.json()

        def crop(low: np.ndarray, high: np.ndarray) -> None:
            centre = (low + high) / 2
            half = float(max(high[0] - low[0], high[1] - low[1]) / 2)
            matrix = _top_view(np.array([*centre, 0.0]), half)
            # the square's corners in NDC, for a rectangle inside the (square) view
            ndc_low = (low - centre) / half
            ndc_high = (high - centre) / half
            polygon = [
                (ndc_low[0], ndc_low[1]),
                (ndc_high[0], ndc_low[1]),
                (ndc_high[0], ndc_high[1]),
                (ndc_low[0], ndc_high[1]),
            ]
            post("/api/reset", {"scope": "unlabelled"})
            post("/api/split", {"view_projection": matrix.reshape(-1).tolist(), "polygon": polygon})

        # Buildings, 3D workflow: connected building footprints on a 1 m grid.
        building = truth == 5
        cells = np.floor(local[building, :2]).astype(np.int64)
        cell_low = cells.min(axis=0)
        grid = np.zeros(tuple(cells.max(axis=0) - cell_low + 1), bool)
        grid[tuple((cells - cell_low).T)] = True
        footprints, n_footprints = ndimage.label(ndimage.binary_dilation(grid, iterations=1))
        which = footprints[tuple((cells - cell_low).T)]
        building_indices = np.flatnonzero(building)
        fits = 0
        for label in range(1, n_footprints + 1):
            members = building_indices[which == label]
            if members.size < 200:
                continue
            low = local[members, :2].min(axis=0) - 0.5
            high = local[members, :2].max(axis=0) + 0.5
            for _ in range(8):  # walls and roof planes, the biggest first
                remaining = members[session.labels[members] == 0]
                if remaining.size < 100:
                    break
                crop(low, high)
                anchor = local[rng.choice(remaining)]
                close = remaining[np.linalg.norm(local[remaining] - anchor, axis=1) < 1.5]
                if close.size < 3:
                    continue
                seeds = local[rng.choice(close, 3, replace=False)]
                answer = client.post(
                    "/api/fit",
                    json={"kind": "plane", "seeds": seeds.tolist(), "tolerance_m": 0.12},
                )
                operations += 1
                if answer.status_code != 200:
                    continue
                fits += 1
                post("/api/assign", {"value": 5})

        # Ground, 2D workflow: top-view squares, then a front-view slab below local ground.
        ground = np.isin(truth, (1, 2))
        tile = 8.0
        keys = np.floor(local[ground, :2] / tile).astype(np.int64)
        tiles, counts = np.unique(keys, axis=0, return_counts=True)
        slabs = 0
        for key in tiles[counts >= 200]:
            low, high = key * tile, (key + 1) * tile
            inside = np.flatnonzero(
                (local[:, 0] >= low[0])
                & (local[:, 0] < high[0])
                & (local[:, 1] >= low[1])
                & (local[:, 1] < high[1])
            )
            if inside.size == 0:
                continue
            floor_z = float(np.percentile(local[inside, 2], 2))  # what the user sees
            crop(low, high)
            centre = np.array([(low[0] + high[0]) / 2, 0.0, floor_z])
            matrix = _front_view(centre, tile)
            top = 0.4 / tile
            polygon = [(-1.0, -1.0), (1.0, -1.0), (1.0, top), (-1.0, top)]
            post("/api/split", {"view_projection": matrix.reshape(-1).tolist(), "polygon": polygon})
            post("/api/assign", {"value": 2})
            slabs += 1
        labels = session.labels.copy()
        session.close()
    seconds = time.perf_counter() - start

    def iou(predicted: np.ndarray, actual: np.ndarray) -> float:
        return float((predicted & actual).sum() / max((predicted | actual).sum(), 1))

    return {
        "n_points": len(truth),
        "operations": operations,
        "building_fits": fits,
        "ground_slabs": slabs,
        "iou_buildings": iou(labels == 5, truth == 5),
        "iou_ground": iou(labels == 2, ground),
        "labelled_fraction": float((labels != 0).mean()),
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, nargs="+", default=[1_000_000, 10_000_000])
    parser.add_argument("--script-points", type=int, default=1_000_000)
    parser.add_argument("--child", choices=["measure", "script"])
    parser.add_argument("--prepared")
    args = parser.parse_args()
    if args.child:
        prepared = json.loads(args.prepared)
        result = child_measure(prepared) if args.child == "measure" else scripted_run(prepared)
        print(json.dumps(result))
        return
    import subprocess

    rows = []
    for n in args.points:
        prepared = prepare(n)
        done = subprocess.run(
            [sys.executable, str(HERE), "--child", "measure", "--prepared", json.dumps(prepared)],
            check=True,
            capture_output=True,
            text=True,
        )
        row = json.loads(done.stdout.strip().splitlines()[-1])
        row["simulate_s"], row["cache_s"] = prepared["simulate_s"], prepared["cache_s"]
        rows.append(row)
        print(json.dumps(row, indent=1), flush=True)
    if not args.script_points:
        return
    prepared = prepare(args.script_points)
    done = subprocess.run(
        [sys.executable, str(HERE), "--child", "script", "--prepared", json.dumps(prepared)],
        check=True,
        capture_output=True,
        text=True,
    )
    script = json.loads(done.stdout.strip().splitlines()[-1])
    print(json.dumps(script, indent=1))
    OUT.mkdir(exist_ok=True)
    (OUT / "labelling.json").write_text(json.dumps({"sizes": rows, "script": script}, indent=2))


if __name__ == "__main__":
    main()
