"""The labelling app on simulated scans: level-of-detail build, a real Chromium session
(first picture, orbit frame rates, a tour of 20 viewpoints), server memory, operation times,
and a scripted labelling run through the HTTP API.

    python benchmarks/bench_labelling.py [--points 10000000 100000000] [--script-points 1000000]
    python benchmarks/bench_labelling.py --quick      # 1 M points, no scripted run

Per scan size (a simulated ``village`` scan, one station; simulation and cache built
beforehand and timed separately), each part in a fresh process:

1. ``build``: the compiled level-of-detail build from the cache
   (:func:`semantic3d.labelling.lod.build_lod`; points/s, CPU, peak RSS), beside the cache's
   spatial tile store (``open_cache_tiles``), the other one-off index a scan gets.
   PotreeConverter 2.0's published rate is 6-9 M points/s on many cores.
2. ``browser``: ``semantic3d label`` as a subprocess (the real server, uvicorn) and Debian's
   Chromium through Playwright with software WebGL (SwiftShader): time to the first picture
   and until the budget is loaded; per point budget (0.25 / 0.5 / 1 / 2 M) the frame times
   while orbiting 60 frames, with the adaptive points per frame (what the page does) and
   with the budget fixed, and (adaptive) 4 gestures that start while the view refines after
   a pause, the first frame timed from the move; beside each, the frames of the idle page
   (nothing drawn), the floor the machine's load sets;
   then a tour of 20 viewpoints, after which the tab's JS heap, the browser's processes'
   RSS, the points kept loaded and the server's peak RSS are read; then each operation's
   time through the HTTP API (split, fit preview, fit, assign of the whole scan, undo, redo,
   counts in view, save). Potree's default budget is 1 M points.
3. ``passes``: the split of the operations above three ways in one process: over the octree
   nodes (what the server does), and as the compiled pass over every point on one thread and
   on numba's threads (the peer); the three masks are checked equal.

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
import os
import resource
import signal
import subprocess
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
USER_CACHE = DATA / "user-cache"


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


def _lod_directory(cache: Path) -> Path:
    from semantic3d.labelling.cachedir import entry_name
    from semantic3d.labelling.lod import LOD_VERSION

    return USER_CACHE / f"{entry_name(cache)}.lod-v{LOD_VERSION}"


def child_build(prepared: dict[str, Any]) -> dict[str, Any]:
    """The compiled level-of-detail build (into the cache folder the server then reuses)."""
    from semantic3d.labelling.lod import build_lod
    from semantic3d.spatial import open_cache_tiles

    cache = Path(prepared["cache"])
    out: dict[str, Any] = {"n_points": prepared["n_points"], "load_before": os.getloadavg()[0]}
    cpu = time.process_time()
    start = time.perf_counter()
    lod = build_lod(cache, _lod_directory(cache))
    out["lod_build_s"] = time.perf_counter() - start
    out["lod_build_cpu_s"] = time.process_time() - cpu
    out["lod_points_per_s"] = lod.n_points / out["lod_build_s"]
    out["lod_points_per_cpu_s"] = lod.n_points / out["lod_build_cpu_s"]
    out["lod_nodes"] = len(lod.nodes)
    out["lod_peak_rss_mb"] = _rss_mb()
    if prepared["n_points"] <= 20_000_000:
        start = time.perf_counter()
        open_cache_tiles(cache)
        out["tile_store_build_s"] = time.perf_counter() - start
    return out


def _server(cache: Path, labels: Path, port: int) -> tuple[subprocess.Popen[str], str]:
    env = {**os.environ, "SEMANTIC3D_CACHE_DIR": str(USER_CACHE), "COLUMNS": "300"}
    command = [sys.executable, "-m", "semantic3d", "label", str(cache), "--labels", str(labels)]
    process = subprocess.Popen(
        [*command, "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
    )
    assert process.stdout is not None
    for line in process.stdout:
        if "?token=" in line:
            return process, line.strip()
    raise RuntimeError("the labelling server did not start")


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _browser_rss_mb() -> float:
    import psutil

    total = 0
    for child in psutil.Process().children(recursive=True):
        try:
            if "chrom" in child.name():
                total += child.memory_info().rss
        except psutil.Error:
            continue
    return total / 2**20


_ORBIT = """async (frames) => {
  const v = window.labelApp.viewer, times = [];
  let shown = 0;
  await new Promise((r) => requestAnimationFrame(r));
  let last = performance.now();
  for (let i = 0; i < frames; i++) {
    const t = v.controls.target, p = v.camera.position, a = (2 * Math.PI) / frames;
    const dx = p.x - t.x, dy = p.y - t.y;
    p.x = t.x + dx * Math.cos(a) - dy * Math.sin(a);
    p.y = t.y + dx * Math.sin(a) + dy * Math.cos(a);
    v.controls.update();
    await new Promise((r) => requestAnimationFrame(r));
    const now = performance.now(); times.push(now - last); last = now; shown += v.stats().points;
  }
  return { times, framePoints: v.framePoints, shown: shown / frames };
}"""

# The floor under the machine's load: frames of the idle page (nothing drawn), same count.
_IDLE_FRAMES = """async (frames) => {
  const times = [];
  await new Promise((r) => requestAnimationFrame(r));
  let last = performance.now();
  for (let i = 0; i < frames; i++) {
    await new Promise((r) => requestAnimationFrame(r));
    const now = performance.now(); times.push(now - last); last = now;
  }
  return times;
}"""

# Gestures that start while the view refines: after each pause (the view at rest refines in
# slices and loads nodes), the camera moves at a moment not tied to a frame; the first frame's
# time counts from that moment.
_RESTARTS = """async ([gestures, frames]) => {
  const v = window.labelApp.viewer, first = [], times = [];
  const frame = () => new Promise((r) => requestAnimationFrame(r));
  const turn = () => {
    const t = v.controls.target, p = v.camera.position, a = Math.PI / 60;
    const dx = p.x - t.x, dy = p.y - t.y;
    p.x = t.x + dx * Math.cos(a) - dy * Math.sin(a);
    p.y = t.y + dx * Math.sin(a) + dy * Math.cos(a);
    v.controls.update();
  };
  for (let g = 0; g < gestures; g++) {
    await new Promise((r) => setTimeout(r, 300 + 150 * g));
    let last = performance.now();
    turn();
    await frame();
    let now = performance.now(); first.push(now - last); last = now;
    for (let i = 1; i < frames; i++) {
      turn();
      await frame();
      now = performance.now(); times.push(now - last); last = now;
    }
  }
  return { first, times };
}"""

_GOTO = """async (k) => {
  const v = window.labelApp.viewer, f = v.frame, c = f.getCenter(v.centre.clone());
  const size = Math.max(f.max.x - f.min.x, f.max.y - f.min.y), a = k * 2.4;
  const r = size * (0.08 + 0.06 * (k % 5)), t = c.clone();
  t.x += 0.3 * size * Math.cos(a * 0.7); t.y += 0.3 * size * Math.sin(a * 0.7);
  v.controls.target.copy(t);
  v.camera.position.set(t.x + r * Math.cos(a), t.y + r * Math.sin(a), t.z + r * 0.4);
  v.controls.update(); v.settleNow();
  await new Promise((r2) => requestAnimationFrame(() => requestAnimationFrame(r2)));
}"""


def _wait_idle(page: Any, timeout_s: float = 120) -> float:
    start = time.perf_counter()
    page.wait_for_function(
        "() => { const s = document.getElementById('status');"
        " return s.dataset.idle === 'true' && !s.textContent.startsWith('0 '); }",
        timeout=timeout_s * 1000,
    )
    return time.perf_counter() - start


def child_browser(prepared: dict[str, Any]) -> dict[str, Any]:
    """Server subprocess + Chromium: first picture, orbit, tour, memory, operations."""
    import httpx
    from playwright.sync_api import sync_playwright

    cache = Path(prepared["cache"])
    out: dict[str, Any] = {"n_points": prepared["n_points"], "load_before": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as scratch:
        port = _free_port()
        server, url = _server(cache, Path(scratch) / "bench.labels", port)
        base, token = url.split("/?token=")
        client = httpx.Client(base_url=base, headers={"X-Semantic3D-Token": token}, timeout=600)
        try:
            for _ in range(600):
                try:
                    client.get("/api/summary")
                    break
                except httpx.TransportError:
                    time.sleep(0.1)
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(
                    executable_path="/usr/bin/chromium",
                    args=[
                        "--no-sandbox",
                        "--use-gl=angle",
                        "--use-angle=swiftshader",
                        "--enable-unsafe-swiftshader",
                        "--enable-precise-memory-info",
                    ],
                )
                page = browser.new_page(viewport={"width": 1280, "height": 800}, bypass_csp=True)
                start = time.perf_counter()
                page.goto(url)
                page.wait_for_function(
                    "() => window.labelApp && window.labelApp.viewer.stats().points > 0",
                    timeout=120_000,
                )
                out["first_picture_s"] = time.perf_counter() - start
                _wait_idle(page)
                out["budget_loaded_s"] = time.perf_counter() - start
                orbit = []
                for adaptive in (True, False):
                    for budget in (250_000, 500_000, 1_000_000, 2_000_000):
                        page.evaluate(
                            "([b, a]) => { const v = window.labelApp.viewer; v.adaptive = a;"
                            " v.setBudget(b); }",
                            [budget, adaptive],
                        )
                        _wait_idle(page)
                        page.wait_for_timeout(1000)  # let the GPU process drain
                        idle = sorted(page.evaluate(_IDLE_FRAMES, 60))
                        result = page.evaluate(_ORBIT, 60)
                        times = sorted(result["times"])
                        row = {
                            "budget": budget,
                            "adaptive": adaptive,
                            "load": os.getloadavg()[0],
                            "fps": 1000 / (sum(times) / len(times)),
                            "median_frame_ms": times[len(times) // 2],
                            "worst_frame_ms": times[-1],
                            "frame_points_end": result["framePoints"],
                            "idle_page_median_worst_frame_ms": [idle[len(idle) // 2], idle[-1]],
                            "mean_points_shown": result["shown"],
                        }
                        if adaptive:
                            restarts = page.evaluate(_RESTARTS, [4, 15])
                            row["restart_first_frame_ms"] = restarts["first"]
                            row["restart_worst_frame_ms"] = max(
                                restarts["first"] + restarts["times"]
                            )
                        orbit.append(row)
                        print(json.dumps(orbit[-1]), file=sys.stderr, flush=True)
                out["orbit"] = orbit
                page.evaluate(
                    "() => { const v = window.labelApp.viewer; v.adaptive = true; v.setBudget(1000000); }"
                )
                cdp = page.context.new_cdp_session(page)
                cdp.send("Performance.enable")
                heap = []
                start = time.perf_counter()
                for k in range(20):
                    page.evaluate(_GOTO, k)
                    _wait_idle(page)
                    metrics = {
                        m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]
                    }
                    heap.append(metrics["JSHeapUsedSize"] / 2**20)
                out["tour_s"] = time.perf_counter() - start
                stats = page.evaluate("window.labelApp.viewer.stats()")
                out["tour_js_heap_mb"] = heap
                out["tour_loaded_points"] = stats["loadedPoints"]
                out["tour_evicted_nodes"] = stats["evicted"]
                out["memory_budget_points"] = page.evaluate("window.labelApp.viewer.memoryBudget")
                out["browser_rss_mb"] = _browser_rss_mb()
                browser.close()
            out["server_peak_rss_after_tour_mb"] = _peak_rss_mb(server.pid)
            out["operations"] = _operations(client, prepared)
            out["server_peak_rss_mb"] = _peak_rss_mb(server.pid)
        finally:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(30)
    return out


def child_operations(prepared: dict[str, Any]) -> dict[str, Any]:
    """Only the operations through HTTP (the server as a subprocess) and its peak RSS."""
    import httpx

    out: dict[str, Any] = {"n_points": prepared["n_points"], "load_before": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as scratch:
        server, url = _server(Path(prepared["cache"]), Path(scratch) / "ops.labels", _free_port())
        base, token = url.split("/?token=")
        client = httpx.Client(base_url=base, headers={"X-Semantic3D-Token": token}, timeout=600)
        try:
            for _ in range(600):
                try:
                    client.get("/api/summary")
                    break
                except httpx.TransportError:
                    time.sleep(0.1)
            out["operations"] = _operations(client, prepared)
            out["server_peak_rss_mb"] = _peak_rss_mb(server.pid)
        finally:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(30)
    return out


def child_passes(prepared: dict[str, Any]) -> dict[str, Any]:
    """The benchmark's split three ways, in process: over the octree nodes (what a split
    does) and as the pass over every point on one thread and on numba's threads; the
    three results are checked equal."""
    from dataclasses import asdict

    from semantic3d.labelling import _op_kernels
    from semantic3d.labelling.blocks import block_threads
    from semantic3d.labelling.delta import empty_bits
    from semantic3d.labelling.node_split import split_flips_by_nodes
    from semantic3d.labelling.opening import open_label_session

    out: dict[str, Any] = {"load_before": os.getloadavg()[0], "threads": block_threads()}
    with tempfile.TemporaryDirectory() as scratch:
        session = open_label_session(
            prepared["cache"], labels_path=Path(scratch) / "passes.labels", cache_dir=USER_CACHE
        )
        try:
            station = np.asarray(prepared["station_m"]) - session.origin
            matrix = _top_view(station, 30.0)
            polygon = np.asarray(SQUARE)
            editable = session.editable_layers()

            def every_point(threads: int) -> Any:
                flip = empty_bits(session.n_points)
                session.map_blocks(
                    lambda start, xyz: _op_kernels.split_flips(
                        xyz, start, session.origin, session.labels, session.working, editable,
                        matrix, polygon, True, flip,
                    ),
                    threads=threads,
                )  # fmt: skip
                return flip

            def by_nodes() -> Any:
                flip = empty_bits(session.n_points)
                out["node_split"] = asdict(
                    split_flips_by_nodes(
                        session, matrix, polygon, keep_inside=True, editable=editable, flip=flip
                    )
                )
                return flip

            flips = []
            for name, run in (
                ("every_point_1_thread", lambda: every_point(1)),
                ("every_point_threads", lambda: every_point(block_threads())),
                ("by_nodes", by_nodes),
            ):
                run()  # compiled kernels and the page cache warm
                cpu, start = time.process_time(), time.perf_counter()
                flips.append(run())
                out[f"{name}_s"] = time.perf_counter() - start
                out[f"{name}_cpu_s"] = time.process_time() - cpu
            out["equal"] = all(np.array_equal(flips[0], f) for f in flips[1:])
        finally:
            session.close()
    out["load_after"] = os.getloadavg()[0]
    return out


def _timed(client: Any, path: str, body: dict[str, Any] | None = None) -> tuple[float, Any]:
    start = time.perf_counter()
    answer = client.get(path) if body is None else client.post(path, json=body)
    seconds = time.perf_counter() - start
    if answer.status_code != 200:
        raise RuntimeError(f"{path}: {answer.status_code} {answer.text}")
    return seconds, answer.json()


def _operations(client: Any, prepared: dict[str, Any]) -> dict[str, Any]:
    """Server time of each operation over every point of the scan (through HTTP)."""
    scan = client.get("/api/scan").json()
    origin = np.asarray(scan["hierarchy"]["origin"])
    station = np.asarray(prepared["station_m"]) - origin
    ground = (station - (0, 0, prepared["station_m"][2])).tolist()
    times: dict[str, Any] = {}
    square = {"view_projection": _top_view(station, 30.0).reshape(-1).tolist(), "polygon": SQUARE}
    times["split_s"], _ = _timed(client, "/api/split", square)
    times["undo_split_s"], _ = _timed(client, "/api/undo", {})
    seeds = [(np.asarray(ground) + d).tolist() for d in ((3, 0, 0), (-2, 2.5, 0), (0, -3, 0))]
    fit = {
        "kind": "plane",
        "seeds": seeds,
        "tolerance_m": 0.1,
        "region": {"kind": "sphere", "centre": ground, "radius_m": 15.0},
    }
    times["fit_preview_s"], preview = _timed(client, "/api/fit/preview", fit)
    times["fit_s"], _ = _timed(client, "/api/fit", {**fit, "model": preview["model"]})
    times["fit_inliers"] = preview["n_inliers"]
    times["undo_fit_s"], _ = _timed(client, "/api/undo", {})
    # A facade-sized region away from the scanner: the fit reads only the nodes meeting it.
    centre = (np.asarray(ground) + np.array([20.0, 5.0, 0.0])).tolist()
    small = {
        **fit,
        "seeds": [
            (np.asarray(centre) + d).tolist() for d in ((2, 0, 0), (-1.5, 1.5, 0), (0, -2, 0))
        ],
        "region": {"kind": "sphere", "centre": centre, "radius_m": 5.0},
    }
    times["fit_preview_5m_s"], preview = _timed(client, "/api/fit/preview", small)
    times["fit_5m_s"], _ = _timed(client, "/api/fit", {**small, "model": preview["model"]})
    times["fit_5m_inliers"] = preview["n_inliers"]
    times["reset_s"], _ = _timed(client, "/api/reset", {"scope": "all"})
    times["assign_whole_scan_s"], _ = _timed(
        client, "/api/assign", {"value": 2, "confirm_whole_scan": True}
    )
    times["undo_assign_s"], _ = _timed(client, "/api/undo", {})
    times["redo_assign_s"], _ = _timed(client, "/api/redo", {})
    view = {"scope": "view", "view_projection": _top_view(station, 60.0).reshape(-1).tolist()}
    times["counts_in_view_s"], _ = _timed(client, "/api/stats", view)
    times["save_s"], _ = _timed(client, "/api/save", {})
    return times


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


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
            cache, labels_path=Path(scratch) / "script.labels", cache_dir=USER_CACHE
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


def _child(kind: str, prepared: dict[str, Any]) -> dict[str, Any]:
    done = subprocess.run(
        [sys.executable, str(HERE), "--child", kind, "--prepared", json.dumps(prepared)],
        check=True,
        stdout=subprocess.PIPE,
        text=True,
    )
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, nargs="+", default=[10_000_000])
    parser.add_argument("--script-points", type=int, default=1_000_000)
    parser.add_argument("--quick", action="store_true", help="1 M points, no scripted run")
    parser.add_argument("--child", choices=["build", "browser", "operations", "passes", "script"])
    parser.add_argument(
        "--operations-only", action="store_true", help="server operations and passes only"
    )
    parser.add_argument("--prepared")
    args = parser.parse_args()
    if args.child:
        prepared = json.loads(args.prepared)
        run = {
            "build": child_build,
            "browser": child_browser,
            "operations": child_operations,
            "passes": child_passes,
            "script": scripted_run,
        }
        print(json.dumps(run[args.child](prepared)))
        return
    if args.quick:
        args.points, args.script_points = [1_000_000], 0
    if args.operations_only:
        for n in args.points:
            row = _child("operations", prepare(n))
            row["passes"] = _child("passes", prepare(n))
            print(json.dumps(row, indent=1), flush=True)
        return
    rows = []
    for n in args.points:
        prepared = prepare(n)
        row = {"simulate_s": prepared["simulate_s"], "cache_s": prepared["cache_s"]}
        row.update(_child("build", prepared))
        row.update(_child("browser", prepared))
        row["passes"] = _child("passes", prepared)
        rows.append(row)
        print(json.dumps(row, indent=1), flush=True)
    script = _child("script", prepare(args.script_points)) if args.script_points else None
    if script:
        print(json.dumps(script, indent=1))
    OUT.mkdir(exist_ok=True)
    name = "labelling-quick.json" if args.quick else "labelling.json"
    (OUT / name).write_text(json.dumps({"sizes": rows, "script": script}, indent=2))


if __name__ == "__main__":
    main()
