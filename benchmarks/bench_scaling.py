"""How the CPU paths scale with threads: one table, each path at 1, 2, 4, 8, 16 threads.

    python benchmarks/bench_scaling.py [--quick] [--points 10000000] [--threads 1 2 4 8 16]
                                       [--oakland ../shared/data/oakland] [--repeat 3]

Thread counts above the machine's cores are left out, so the same command gives the whole
table on a 16-core machine. Every measurement runs in a fresh process capped at ``N``
threads (``NUMBA_NUM_THREADS`` = ``OMP_NUM_THREADS`` = N and
:func:`semantic3d.core.threads.set_thread_limit`), warmed up first (numba's cached
kernels loaded; the best of ``--repeat`` runs, or of more where they add up to under
:data:`MIN_TIMED_S`), with the allocator policy of the command
line's compute commands (:func:`semantic3d.core.allocator.keep_freed_memory`), on the same
files, in the same run:

- ``iter_points``: an ASCII scan (``--points`` lines of the street scene) streamed
  through :func:`semantic3d.io.iter_ascii_points`; peer: ``pyarrow.csv.read_csv`` with
  ``pyarrow.set_cpu_count(N)`` (its block reader, every block on its own thread);
- ``read_labels``: the scan's ``.labels`` 32 times over (one file; 4 times that on 16
  cores: :func:`label_copies`); peer: ``pyarrow.csv.read_csv`` of the same file;
- ``simulate``: :func:`semantic3d.datasets.simulator.simulate` of that scan (text written);
- ``predict``: the covariance baseline on that one scan, tiled whatever its size
  (``predict_scan``, labels and run record written), with the model trained below;
- ``predict_data``: the covariance baseline on every scan of the training folder (below)
  at once, as ``baseline covariance predict --data`` labels them
  (:func:`semantic3d.baselines.common.prediction.predict_scans`, a scan per 4 threads at a
  time, labels and run records written), with a model trained on that folder;
- ``train``: :func:`semantic3d.baselines.covariance.training.train_covariance_model` on the
  Oakland scans (``--oakland``; three simulated scans when absent), default configuration;
- ``compute`` and ``bandwidth``: the machine's own ceilings (``_ceilings.py``): arithmetic
  in registers, the same on every thread, and a stream through arrays far beyond the
  caches; a path's speed-up is read against theirs (the last table: from 2 threads to the
  most, as a share of the compute ceiling's);
- ``evaluate``: :func:`semantic3d.evaluation.evaluate_submission` of 8 scans (links to the
  scan's labels 4 times over, 16 on 16 cores, and to a prediction of them wrong in runs of
  ~100 lines, a tenth of them), label pairs per second; peer: both files of each scan read
  by ``pyarrow.csv.read_csv`` (N threads) and counted with ``numpy.bincount``, whose
  matrix the evaluation's must equal (the run stops where it does not).

Each row gives the rate (items per second, wall clock), CPU seconds (and their ratio to the
peer's, which a loaded machine disturbs less than wall time), the system CPU seconds and
minor page faults of the timed run (each 4 KiB of fresh memory is one where numpy gets no
transparent huge pages: the first line says the kernel's mode), the mean number of the
process's threads running or ready to run while it worked (sampled every 2 ms: a
load-independent view of how parallel it was), the peer's rate at the same count, the floor
where a path must read files (``read_labels``, ``evaluate``: the same files read on the
same threads as the readers read them, 512 KiB positioned reads from compiled code, nothing
parsed, and for ``read_labels`` its result, a byte a label, written once into new memory on
those threads; items per second at that speed, and the path's rate over it), the peak
resident memory of the path's runs and of the peer's, apart (the process's ``VmHWM``,
reset before each on Linux; the process's whole peak elsewhere, the interpreter and the
imports included) and the SHA-256 of what ``simulate``, ``predict`` and ``predict_data``
wrote (the same at every count, or a line says they differ). Per path, the Amdahl serial fraction ``s`` is fitted to the speed-ups over 1
thread (least squares on ``1/S(n) = s + (1 - s)/n``), with the speed-up it predicts on 16
threads; with only 1 and 2 threads (a 2-core machine) the fit is exact and the 16-thread
figure a prediction. ``s`` is also estimated from the 2-thread run's thread samples (time
with one thread running over the time one thread would take), which a loaded machine
disturbs less than wall time. The load average is printed beside every row: compare rows of
one run. ``--where`` also names the code that runs while at most a quarter of the threads
do, at the largest thread count: the serial parts to remove next. ``--timeline`` records
one more ``predict`` run at the largest count on a timeline
(:mod:`semantic3d.core.timeline`: the spill, each tile's pyramid, features and the parts of
their levels, forest and cut, every square of the cuts, the labels written) and prints what
ran after the last tile started: which tiles' chains of steps the other threads waited for
(with the threads of a tile's parts at their start and end). The spans go to
``bench_scaling_timeline.json``.
Writes ``bench_scaling.json`` into ``--out`` (``benchmarks/out``).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
PATHS = (
    "compute",
    "bandwidth",
    "iter_points",
    "read_labels",
    "simulate",
    "predict",
    "predict_data",
    "train",
    "evaluate",
)
CEILINGS = ("compute", "bandwidth")
"""The machine's own scaling (``_ceilings.py``), not a path of the package."""
SPIN_STEPS = 1 << 27  # multiply-add rounds a thread: about 0.3 s
TRIAD_BYTES = 3 << 29  # the three arrays of the bandwidth ceiling (1.5 GiB), beyond any cache
TRIAD_ROUNDS = 8
PEERS = {
    "iter_points": "pyarrow.csv",
    "read_labels": "pyarrow.csv",
    "evaluate": "pyarrow.csv + numpy.bincount",
}
N_EVALUATED_SCANS = 8
PREDICTION_WRONG = 0.1  # the evaluated prediction's share of runs of wrong labels
WARM_POINTS = 1_000_000  # the scan labelled once before the timed runs (kernels compiled)
WHERE_TOP = 12
MIN_TIMED_S = 1.5
"""A measurement's runs go on past ``--repeat`` until they add up to this many seconds (at
most :data:`MAX_RUNS`): a 10 M-line read on 16 threads takes about 0.1 s, and the best of
one or three such runs moved our ratio to pyarrow by a third between two runs."""
MAX_RUNS = 25


# --- the measured process ------------------------------------------------------------------


class _Sampler:
    """Counts this process's threads in state R (running or ready) every 2 ms.

    With ``few`` (a thread count), also names the code that runs while at most that many
    threads do: per running thread its innermost frames of the package (a Python thread)
    or ``[compiled worker]`` (a numba / OpenMP thread, whose caller's frames are then
    those of the Python thread waiting in the compiled call).
    """

    def __init__(self, few: int | None = None) -> None:
        self.counts: Counter[int] = Counter()
        self.few = few
        self.stacks: Counter[str] = Counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> _Sampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        me = threading.get_native_id()
        while not self._stop.is_set():
            running = []
            for task in Path("/proc/self/task").iterdir():
                if int(task.name) == me:
                    continue
                try:
                    data = (task / "stat").read_bytes()
                except OSError:
                    continue
                end = data.rindex(b")")
                if data[end + 2 : end + 3] == b"R":
                    running.append(int(task.name))
            self.counts[len(running)] += 1
            if self.few is not None and 0 < len(running) <= self.few:
                self._name(running)
            time.sleep(0.002)

    def _name(self, running: list[int]) -> None:
        python = {t.native_id: t.ident for t in threading.enumerate()}
        frames = sys._current_frames()
        for native in running:
            ident = python.get(native)
            if ident is None:
                self.stacks["[compiled worker]"] += 1
            else:
                self.stacks[_stack(frames.get(ident))] += 1


def _stack(frame: Any, depth: int = 4) -> str:
    """The innermost ``depth`` frames of the package: ``file:function:line < ...``."""
    names: list[str] = []
    while frame is not None and len(names) < depth:
        code = frame.f_code
        if "semantic3d" in code.co_filename:
            names.append(f"{Path(code.co_filename).name}:{code.co_name}:{frame.f_lineno}")
        frame = frame.f_back
    return " < ".join(names) or "(outside the package)"


def _usage() -> tuple[float, int]:
    """This process's system CPU seconds and minor page faults so far (0, 0 without
    ``resource``)."""
    try:
        import resource
    except ImportError:  # not on Unix
        return 0.0, 0
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_stime, usage.ru_minflt


def transparent_huge_pages() -> str:
    """The kernel's transparent huge page mode (``[madvise]``: numpy's large arrays get
    them), or "unknown": without them every 4 KiB of a fresh array is a page fault."""
    try:
        text = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return "unknown"
    return next((word.strip("[]") for word in text.split() if word.startswith("[")), "unknown")


def _reset_peak_memory() -> bool:
    """Start this process's peak resident memory afresh (Linux: ``clear_refs`` 5), so the
    next :func:`_peak_memory` covers what ran since; False where it cannot."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _peak_memory() -> int:
    """This process's peak resident memory in bytes since the last reset (``VmHWM``), or
    over its whole life where there is no such reset (``ru_maxrss``); 0 where neither is
    known."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import resource
    except ImportError:
        return 0
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def _measure(run: Callable[[], int], few: int | None = None) -> dict[str, Any]:
    load = os.getloadavg()[0]
    system, faults = _usage()
    cpu, wall = time.process_time(), time.perf_counter()
    with _Sampler(few) as sampler:
        items = run()
    wall = time.perf_counter() - wall
    total = max(1, sum(sampler.counts.values()))
    system_after, faults_after = _usage()
    return {
        "items": items,
        "wall_s": wall,
        "cpu_s": time.process_time() - cpu,
        "system_s": system_after - system,  # in the kernel: reads, writes, page faults
        "page_faults": faults_after - faults,
        "running": {str(k): v for k, v in sorted(sampler.counts.items())},
        "load": load,
        # share of all samples at which each piece of code ran while few threads did
        "few_running": [
            [stack, count / total] for stack, count in sampler.stacks.most_common(WHERE_TOP)
        ],
    }


def _best(
    run: Callable[[], int], repeat: int, few: int | None = None, min_s: float = MIN_TIMED_S
) -> dict[str, Any]:
    """The fastest of ``repeat`` measured runs, or of more while they add up to less than
    ``min_s`` (:data:`MIN_TIMED_S`; at most :data:`MAX_RUNS`); its ``runs`` says how many."""
    runs = [_measure(run, few)]
    while len(runs) < repeat or (sum(m["wall_s"] for m in runs) < min_s and len(runs) < MAX_RUNS):
        runs.append(_measure(run, few))
    return {**min(runs, key=lambda m: m["wall_s"]), "runs": len(runs)}


def _digest(paths: list[Path]) -> str:
    """SHA-256 of the files' bytes, one after the other (first 12 hex digits)."""
    digest = hashlib.sha256()
    for path in paths:
        with path.open("rb") as stream:
            while block := stream.read(1 << 24):
                digest.update(block)
    return digest.hexdigest()[:12]


class _ReadFloor:
    """The files' bytes read on ``n_threads`` threads as the package's readers read them
    (compiled positioned reads of 512 KiB blocks, each thread a run of blocks into its own
    buffer, which stays in cache), nothing parsed, and, with ``result_bytes``, a fresh
    array of that many bytes written once on the same threads (each a contiguous slice,
    its pages first touched there): the floor of a path that must read the files and hand
    back its result in new memory. A call returns ``items`` (what the path counts for the
    bytes)."""

    BLOCK = 1 << 19

    def __init__(
        self, paths: list[Path], n_threads: int, items: int, result_bytes: int = 0
    ) -> None:
        self.items = items
        self.n_threads = n_threads
        self.result_bytes = result_bytes
        self.sizes = {path: path.stat().st_size for path in paths}

    def __call__(self) -> int:
        import numpy as np

        import _ceilings

        for path, size in self.sizes.items():
            fd = os.open(path, os.O_RDONLY)
            try:
                read = _ceilings.read_file(fd, size, self.BLOCK, self.n_threads)
            finally:
                os.close(fd)
            if read != size:
                raise SystemExit(f"the floor read {read} of the {size} bytes of {path}")
        if self.result_bytes:
            _ceilings.fill(np.empty(self.result_bytes, np.uint8), self.n_threads)
        return self.items


def _pyarrow_table(path: Path, n_threads: int, columns: list[str]) -> Any:
    """The space-separated text file read by ``pyarrow.csv`` on ``n_threads`` threads."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    pa.set_cpu_count(n_threads)
    pa.set_io_thread_count(n_threads)
    read = pacsv.ReadOptions(column_names=columns, use_threads=True)
    parse = pacsv.ParseOptions(delimiter=" ")
    return pacsv.read_csv(path, read_options=read, parse_options=parse)


def _pyarrow_rows(path: Path, n_threads: int, columns: list[str]) -> int:
    return int(_pyarrow_table(path, n_threads, columns).num_rows)


def child(job: dict[str, Any]) -> dict[str, Any]:
    """One measurement in this (fresh, capped) process, with the allocator policy the
    command line's compute commands apply (freed memory kept for reuse)."""
    from semantic3d.core.allocator import keep_freed_memory
    from semantic3d.core.threads import set_thread_limit

    keep_freed_memory()
    n = int(job["threads"])
    set_thread_limit(n)
    path, work = job["path"], Path(job["work"])
    scan = Path(job.get("scan", ""))  # absent for the paths that read no scan
    outputs: list[Path] = []  # files the measured runs wrote, digested after them
    floor: Callable[[], int] | None = None  # the reads a path cannot do without, alone
    check: Callable[[], None] | None = None  # raises unless the path's result is the peer's
    if path == "compute":
        import _ceilings

        def run() -> int:
            _ceilings.spin(n, SPIN_STEPS)
            return n * SPIN_STEPS * _ceilings.CHAINS  # multiply-adds

        run_small, peer = None, None
    elif path == "bandwidth":
        import numpy as np

        import _ceilings

        size = TRIAD_BYTES // 24
        arrays = [np.empty(size) for _ in range(3)]
        for array in arrays:  # each thread first touches the slice it streams
            _ceilings.triad(array, array, array, n)
        arrays[1][:] = 1.0
        arrays[2][:] = 2.0

        def run() -> int:
            for _ in range(TRIAD_ROUNDS):
                _ceilings.triad(*arrays, n)
            return TRIAD_ROUNDS * 3 * 8 * size  # bytes read and written

        run_small, peer = None, None
    elif path == "iter_points":
        from semantic3d.io import iter_ascii_points

        def run() -> int:
            return sum(chunk.n_points for chunk in iter_ascii_points(scan))

        run_small: Callable[[], int] | None = None  # the warm-up reads the scan (cached pages)
        peer: Callable[[], int] | None = lambda: _pyarrow_rows(scan, n, list("xyzirgb"))  # noqa: E731
    elif path == "read_labels":
        from semantic3d.io import read_labels

        labels = Path(job["labels"])  # the evaluated files' labels, one after another

        def run() -> int:
            return int(read_labels(labels).size)

        run_small = None  # a small file is parsed by numpy: the warm-up reads the large one
        peer = lambda: _pyarrow_rows(labels, n, ["label"])  # noqa: E731
        items = labels.stat().st_size // 2  # one result byte a label
        floor = _ReadFloor([labels], n, items, result_bytes=items)
    elif path == "simulate":
        from semantic3d.datasets.simulator import simulate

        def run() -> int:
            made = simulate(
                "street", out=work / f"simulate{n}", n_points=int(job["points"]), seed=2
            )
            outputs.extend(p for scan in made.scans for p in (scan.points_path, scan.labels_path))
            return made.n_points

        run_small = lambda: simulate("street", out=work / f"warm{n}", n_points=20_000).n_points  # noqa: E731
        peer = None
    elif path == "predict":
        from semantic3d.baselines.covariance.persistence import load_model
        from semantic3d.baselines.covariance.predict import predict_scan

        model = load_model(job["model"])

        def run() -> int:
            out = work / f"predict{n}.labels"
            outputs.append(out)
            return predict_scan(model, scan, out_path=out, workdir=work, overwrite=True).n_points

        def run_small() -> int:
            out = work / f"warm{n}.labels"
            small = Path(job["small"])
            return predict_scan(model, small, out_path=out, workdir=work, overwrite=True).n_points

        peer = None
    elif path == "predict_data":
        from semantic3d.baselines.common.prediction import predict_scans, scans_at_once
        from semantic3d.baselines.common.submission import find_scans_to_label
        from semantic3d.baselines.covariance.persistence import load_model

        model = load_model(job["data_model"])
        scans = find_scans_to_label(Path(job["training"]))

        def run() -> int:
            out = work / f"predict_data{n}"
            made = predict_scans(
                model, scans, out, overwrite=True, parallel_scans=scans_at_once(len(scans))
            )
            outputs.extend(out / scan.output_name for scan in scans)
            return made.n_points

        run_small = None
        peer = None
    elif path == "train":
        from semantic3d.baselines.covariance.config import CovarianceConfig
        from semantic3d.baselines.covariance.training import (
            find_labelled_scans,
            train_covariance_model,
        )

        scans = find_labelled_scans(Path(job["training"]))

        def run() -> int:
            model = train_covariance_model(scans, config=CovarianceConfig())
            return sum(model.n_training_points.values())

        def run_small() -> int:  # the kernels and scikit-learn loaded
            return len(
                train_covariance_model(scans[:2], config=CovarianceConfig()).classifier.classes_
            )

        peer = None
    elif path == "evaluate":
        from semantic3d.evaluation import custom_challenge, evaluate_submission

        truth, predicted = work / "truth", work / "submission"
        copies = int(job.get("label_copies", 4))  # the scan's labels in each file

        def run() -> int:
            evaluate_submission(predicted, challenge=custom_challenge(truth))
            return copies * N_EVALUATED_SCANS * int(job["scan_points"])  # label pairs read

        run_small = None
        files = [(path, predicted / path.name) for path in sorted(truth.glob("*.labels"))]
        peer = lambda: int(_pyarrow_confusion(files, n, 8).sum())  # noqa: E731

        def check() -> None:
            _same_counts(
                evaluate_submission(predicted, challenge=custom_challenge(truth)).confusion,
                _pyarrow_confusion(files, n, 8)[1:, 1:],  # the scored classes
            )

        floor = _ReadFloor(
            [path for pair in files for path in pair],
            n,
            copies * N_EVALUATED_SCANS * int(job["scan_points"]),
        )
    else:
        raise SystemExit(f"unknown path {path}")
    if run_small is not None:
        run_small()
    else:
        run()
    repeat = max(1, int(job.get("repeat", 1)))
    few = job.get("few")
    _reset_peak_memory()  # the warm-up's peak counts too: it ran the same work, or less
    min_s = float(job.get("min_seconds", MIN_TIMED_S))
    result: dict[str, Any] = {"ours": _best(run, repeat, few, min_s)}
    result["ours"]["peak_bytes"] = _peak_memory()
    if outputs:  # the last run's files: the same digest at every thread count
        result["digest"] = _digest(sorted(set(outputs)))
    if job.get("timeline"):  # one more run, its steps on a timeline
        from semantic3d.core.timeline import recording

        with recording() as timeline:
            run()
        result["timeline"] = {
            "end_s": timeline.end_s,
            "spans": [step.to_dict() for step in timeline.spans],
        }
    if peer is not None:
        peer_apart = _reset_peak_memory()
        peer()
        result["peer"] = _best(peer, repeat, min_s=min_s)
        if peer_apart:  # else the process's peak, ours included: not the peer's
            result["peer"]["peak_bytes"] = _peak_memory()
    if floor is not None:
        floor()
        result["floor"] = _best(floor, repeat, min_s=min_s)
    if check is not None:
        check()
        result["agrees_with_peer"] = True
    return result


# --- the driver ---------------------------------------------------------------------------
def label_copies(cores: int) -> int:
    """The scan's labels in each evaluated file (``read_labels`` reads 8 files' worth):
    4 for every 4 cores, at least 4, so that a run on many threads lasts long enough to
    time (on 16 cores, 4 copies were read in 0.07-0.14 s)."""
    return 4 * max(1, cores // 4)


def _run_child(job: dict[str, Any]) -> dict[str, Any]:
    n = str(job["threads"])
    env = dict(os.environ, NUMBA_NUM_THREADS=n, OMP_NUM_THREADS=n, OMP_WAIT_POLICY="passive")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT / "src"), env.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, __file__, "--child", json.dumps(job)],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode:
        raise SystemExit(f"{job['path']} on {n} threads failed:\n{done.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def amdahl(speedups: dict[int, float]) -> float | None:
    """Serial fraction ``s`` minimising the squared error of ``1/S(n) = s + (1 - s)/n``."""
    points = [(n, s) for n, s in speedups.items() if n > 1]
    if not points:
        return None
    num = sum((1 - 1 / n) * (1 / s - 1 / n) for n, s in points)
    den = sum((1 - 1 / n) ** 2 for n, _ in points)
    return min(1.0, max(0.0, num / den))


def profile_fraction(running: dict[str, int], n_threads: int) -> float:
    """Serial fraction from thread samples of an ``n_threads`` run: samples with at most one
    thread running, over the samples weighted by the threads they kept busy."""
    counts = {int(k): v for k, v in running.items()}
    serial = counts.get(0, 0) + counts.get(1, 0)
    weighted = sum(v * max(1, min(k, n_threads)) for k, v in counts.items())
    return serial / weighted if weighted else float("nan")


def _compile_prediction(model: Any, work: Path, n_points: int) -> None:
    """Label a scan of ``n_points`` once on every thread, before any timed run: on a
    machine with no cached kernels, the kernels only a large scan reaches (a dense tile's
    parts, the graph's squares) are compiled and cached here, not in a timed run (the
    children warm up on a small scan, which does not reach them)."""
    from semantic3d.baselines.covariance.predict import predict_scan
    from semantic3d.datasets.simulator import simulate

    warm = simulate("street", out=work / "warm", n_points=n_points, seed=5).scans[0]
    predict_scan(model, warm.points_path, out_path=work / "warm.labels", workdir=work)


SCAN_READERS = frozenset({"iter_points", "read_labels", "predict", "evaluate"})
"""The paths that read the simulated scan (or its labels); the others need none of it."""


def _prepare(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """The scans, the training data, a model and the submission the chosen paths read
    (nothing for the ceilings and ``simulate``: a run of those alone starts at once)."""
    from semantic3d.core.threads import available_cores
    from semantic3d.datasets.simulator import simulate

    paths = set(args.paths)
    shared: dict[str, Any] = {"points": args.points, "work": str(work)}
    if paths & {"predict", "predict_data", "train"}:
        shared["training"] = str(_training_folder(Path(args.oakland), work))
    if "predict_data" in paths:
        shared["data_model"] = str(_data_model(Path(shared["training"]), work))
    if not paths & SCAN_READERS:
        return shared
    scan = simulate("street", out=work / "scan", n_points=args.points, seed=1).scans[0]
    shared.update(scan=str(scan.points_path), scan_points=scan.n_points)
    if "predict" in paths:
        small = simulate("street", out=work / "small", n_points=30_000, seed=3).scans[0]
        model = _tiled_model(Path(shared["training"]), work, min(args.points, WARM_POINTS))
        shared.update(small=str(small.points_path), model=str(model))
    if paths & {"read_labels", "evaluate"}:
        shared.update(_label_files(scan.labels_path, work, label_copies(available_cores())))
    return shared


def _training_folder(oakland: Path, work: Path) -> Path:
    """The Oakland scans where they are, else three simulated scenes."""
    from semantic3d.datasets.simulator import simulate

    if oakland.is_dir():
        return oakland
    training = work / "training"
    training.mkdir(exist_ok=True)
    for scene, seed in (("street", 4), ("village", 4), ("square", 4)):
        made = simulate(scene, out=work / f"t{scene}", n_points=200_000, seed=seed).scans[0]
        made.points_path.rename(training / f"{scene}.txt")
        made.labels_path.rename(training / f"{scene}.labels")
    return training


def _tiled_model(training: Path, work: Path, warm_points: int) -> Path:
    """A model trained on the training folder that labels any scan tile by tile (the path
    of a large scan), its kernels compiled on a warm-up scan; the path of its file."""
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.persistence import save_model
    from semantic3d.baselines.covariance.training import (
        find_labelled_scans,
        train_covariance_model,
    )

    model = train_covariance_model(find_labelled_scans(training), config=CovarianceConfig())
    tiled = dataclasses.replace(
        model,
        config=dataclasses.replace(
            model.config,
            prediction=dataclasses.replace(model.config.prediction, max_points_in_memory=0),
        ),
    )
    save_model(tiled, work / "model.s3dm")
    _compile_prediction(tiled, work, warm_points)
    return work / "model.s3dm"


def _data_model(training: Path, work: Path) -> Path:
    """A model trained on the training folder with the default configuration, for
    labelling that folder's scans (``predict_data``); the path of its file."""
    from semantic3d.baselines.covariance.config import CovarianceConfig
    from semantic3d.baselines.covariance.persistence import save_model
    from semantic3d.baselines.covariance.training import (
        find_labelled_scans,
        train_covariance_model,
    )

    model = train_covariance_model(find_labelled_scans(training), config=CovarianceConfig())
    save_model(model, work / "data_model.s3dm")
    return work / "data_model.s3dm"


def _same_counts(ours: Any, peer: Any) -> None:
    """Raise unless the path's counts are the peer's (a fast wrong answer is no answer)."""
    if ours.shape != peer.shape or (ours != peer).any():
        raise SystemExit(f"the counts differ from the peer's:\n{ours}\nagainst\n{peer}")


def _label_files(truth: Path, work: Path, copies: int) -> dict[str, Any]:
    """One file of every evaluated scan's labels for ``read_labels``, and the truth and
    submission folders ``evaluate`` compares: hard links of one file of ``copies`` copies
    of the scan's labels, and of one of a prediction of them (:func:`_prediction`)."""
    (work / "labels").mkdir()
    labels = work / "labels" / "many.labels"
    text = truth.read_bytes()
    per_scan = {"truth": text, "submission": _prediction(text)}
    with labels.open("wb") as stream:
        for _ in range(copies * N_EVALUATED_SCANS):
            stream.write(text)
    for folder, scan_text in per_scan.items():
        one = work / "labels" / f"{folder}.labels"
        with one.open("wb") as stream:
            for _ in range(copies):
                stream.write(scan_text)
        (work / folder).mkdir()
        for number in range(N_EVALUATED_SCANS):
            os.link(one, work / folder / f"scan{number}.labels")
    return {"label_copies": copies, "labels": str(labels)}


def _prediction(truth: bytes) -> bytes:
    """A prediction of ``d\\n`` ground truth as a classifier's differs from it: wrong in
    runs (a tenth of the lines, in runs of ~100 lines: a wrong object or surface), every
    unlabelled point given a class; the same bytes every run."""
    import numpy as np

    values = np.frombuffer(truth, np.uint8)[0::2] - ord("0")
    rng = np.random.default_rng(11)
    runs = values.size // 50 + 2  # twice the lines, on average
    wrong = np.repeat(rng.random(runs) < PREDICTION_WRONG, rng.geometric(0.01, runs))
    predicted = np.where(wrong[: values.size], values % 8 + 1, np.maximum(values, 1))
    text = np.empty(2 * values.size, np.uint8)
    text[0::2] = predicted + ord("0")
    text[1::2] = ord("\n")
    return text.tobytes()


def _pyarrow_confusion(pairs: list[tuple[Path, Path]], n_threads: int, n_classes: int) -> Any:
    """The confusion matrix as a user would count it without the package: each pair of
    files read by ``pyarrow.csv`` (its block reader on ``n_threads`` threads), the values
    counted with ``numpy.bincount``; ``(n_classes + 1,) * 2`` counts, label 0 (unlabelled)
    included, rows ground truth."""
    import numpy as np

    size = n_classes + 1
    table = np.zeros(size * size, np.int64)
    for truth, predicted in pairs:
        t, p = (
            _pyarrow_table(path, n_threads, ["label"]).column(0).to_numpy()
            for path in (truth, predicted)
        )
        if t.size != p.size:
            raise SystemExit(f"{truth} and {predicted} differ in length")
        table += np.bincount(t * size + p, minlength=size * size)
    return table.reshape(size, size)


def _open_at(spans: list[dict[str, Any]], t: float) -> list[dict[str, Any]]:
    return [step for step in spans if step["start_s"] <= t < step["end_s"]]


def _print_timeline(timeline: dict[str, Any], n: int) -> None:
    """What a ``predict`` run's steps took, and what the threads waited for at its end."""
    spans: list[dict[str, Any]] = timeline["spans"]
    end = float(timeline["end_s"])
    print(f"\nTimeline of one predict run on {n} threads: {end:.2f} s")
    print(
        f"{'step':<12} {'count':>6} {'first s':>8} {'last end':>8} {'wall sum':>9} "
        f"{'CPU sum':>8} {'longest':>8}"
    )
    named: dict[str, list[dict[str, Any]]] = {}
    for step in spans:
        named.setdefault(step["name"], []).append(step)
    for name, steps in named.items():
        walls = [step["end_s"] - step["start_s"] for step in steps]
        print(
            f"{name:<12} {len(steps):>6} {min(s['start_s'] for s in steps):>8.2f} "
            f"{max(s['end_s'] for s in steps):>8.2f} {sum(walls):>9.2f} "
            f"{sum(s['cpu_s'] for s in steps):>8.2f} {max(walls):>8.2f}"
        )
    tiles = named.get("tile", [])
    if not tiles:
        return
    first = min(t["start_s"] for t in tiles)
    last_start = max(t["start_s"] for t in tiles)
    last_end = max(t["end_s"] for t in tiles)
    print(
        f"tiles: {len(tiles)} from {first:.2f} s; the last started at {last_start:.2f} s, "
        f"the last ended at {last_end:.2f} s: {last_end - last_start:.2f} s "
        f"({(last_end - last_start) / max(end, 1e-9):.0%} of the run) with no tile waiting"
    )
    slices = 16
    step_s = max(last_end - first, 1e-9) / slices
    print("open at each sixteenth of the tiles' time (tiles / cut squares / features):")
    middles = [first + (k + 0.5) * step_s for k in range(slices)]
    kinds = [tiles, named.get("cut square", []), named.get("features", [])]
    print("  " + " ".join("/".join(str(len(_open_at(k, t))) for k in kinds) for t in middles))
    children: dict[int, list[dict[str, Any]]] = {}
    for step in spans:
        children.setdefault(step["parent"], []).append(step)

    def below(number: int) -> list[dict[str, Any]]:
        found = []
        for child in children.get(number, []):
            found.append(child)
            found.extend(below(child["number"]))
        return found

    def describe(tile: dict[str, Any]) -> str:
        steps = below(tile["number"])
        parts = []
        for name in ("features", "forest", "squares"):
            mine = [s for s in steps if s["name"] == name]
            if mine:
                threads = mine[0]["attrs"].get("threads")
                parts.append(
                    f"{name} {mine[0]['start_s']:.2f}-{mine[0]['end_s']:.2f}"
                    + ("" if threads is None else f" on {threads}")
                )
        levels = [s for s in steps if s["name"] == "levels"]
        if levels:
            attrs = levels[0]["attrs"]
            parts.append(
                f"levels {attrs.get('levels')} in {attrs.get('parts')} parts "
                f"{levels[0]['start_s']:.2f}-{levels[0]['end_s']:.2f} on "
                f"{attrs.get('threads')}-{attrs.get('threads_after')}"
            )
        squares = [s for s in steps if s["name"] == "cut square"]
        if squares:
            longest = max(squares, key=lambda s: s["end_s"] - s["start_s"])
            parts.append(
                f"{len(squares)} squares on {len({s['thread'] for s in squares})} threads, "
                f"the longest {longest['end_s'] - longest['start_s']:.2f} s "
                f"({longest['attrs'].get('rows')} rows)"
            )
        return (
            f"  tile {tile['attrs'].get('tile')}: {tile['attrs'].get('points'):,} points, "
            f"{tile['attrs'].get('threads')} threads, {tile['start_s']:.2f}-{tile['end_s']:.2f}: "
            + "; ".join(parts)
        )

    # the tiles' shares of the threads go by their work: the largest shares should start
    # together and end about together
    print("the four tiles given the most threads (start, end: seconds):")
    for tile in sorted(tiles, key=lambda t: (-t["attrs"].get("threads", 1), t["start_s"]))[:4]:
        print(describe(tile))
    print("the tiles still running when the last one started (start, end: seconds):")
    for tile in sorted(_open_at(tiles, last_start), key=lambda t: -t["end_s"])[:8]:
        print(describe(tile))


def _print_against_the_machine(summary: dict[str, dict[str, Any]], counts: list[int]) -> None:
    """Each path's speed-up from 2 threads (1 where 2 was not run) to the most, beside the
    machine's own: the compute ceiling's is the most a compute-bound path can gain."""
    if "compute" not in summary or len(counts) < 2:
        return
    low = 2 if 2 in counts and counts[-1] > 2 else counts[0]
    top = counts[-1]

    def gain(path: str) -> float:
        rates = summary[path]["rates"]
        return float(rates[top] / rates[low])

    print(
        f"\nAgainst the machine: speed-up from {low} to {top} threads, and its share of the "
        f"compute ceiling's ({gain('compute'):.2f}x"
        + (f"; bandwidth {gain('bandwidth'):.2f}x" if "bandwidth" in summary else "")
        + ")"
    )
    for path in summary:
        if path not in CEILINGS:
            print(f"{path:<12} {gain(path):5.2f}x  {gain(path) / gain('compute'):4.0%}")


def _print_where(rows: list[dict[str, Any]], n: int) -> None:
    few = max(1, n // 4)
    print(f"\nWhere at most {few} of {n} threads ran (share of all samples; one line a thread)")
    for row in rows:
        if row["threads"] != n or not row.get("few_running"):
            continue
        samples = {int(k): v for k, v in row["running"].items()}
        share = sum(v for k, v in samples.items() if 0 < k <= few) / max(1, sum(samples.values()))
        print(f"{row['path']}: {share:.0%} of the samples")
        for stack, part in row["few_running"]:
            print(f"  {part:6.1%}  {stack}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--points", type=int, default=10_000_000)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
    parser.add_argument("--oakland", default=str(ROOT.parent / "shared" / "data" / "oakland"))
    parser.add_argument("--repeat", type=int, default=3, help="Best of this many runs.")
    parser.add_argument("--quick", action="store_true", help="1 M points, best of 2.")
    parser.add_argument(
        "--min-seconds",
        type=float,
        default=MIN_TIMED_S,
        help="Repeat a measurement past --repeat until its runs add up to this (default 1.5).",
    )
    parser.add_argument("--workdir", default=None, help="Scratch folder (default: /tmp).")
    parser.add_argument(
        "--out", default=str(OUT), help="Folder of the JSON results (default: benchmarks/out)."
    )
    parser.add_argument(
        "--where",
        action="store_true",
        help="Also name the code running while at most a quarter of the threads do "
        "(at least one), for the largest thread count.",
    )
    parser.add_argument(
        "--timeline",
        action="store_true",
        help="Record one more predict run at the largest thread count on a timeline and "
        "say what ran after the last tile started.",
    )
    parser.add_argument(
        "--oversubscribe",
        action="store_true",
        help="Also run thread counts above the cores (their times mean nothing; with "
        "--timeline, how the threads are shared out among the tiles does).",
    )
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return
    if args.quick:
        args.points, args.repeat = 1_000_000, 2
    sys.path.insert(0, str(ROOT / "src"))
    from semantic3d.core.threads import available_cores

    cores = available_cores()
    counts = sorted({n for n in args.threads if n <= cores or args.oversubscribe})
    print(
        f"{cores} cores, threads {counts}, {args.points:,} points; "
        f"load average {os.getloadavg()[0]:.2f} before preparing; transparent huge pages "
        f"{transparent_huge_pages()}"
    )
    rows: list[dict[str, Any]] = []
    summary: dict[str, dict[str, Any]] = {}
    timelines: dict[int, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-scaling-", dir=args.workdir) as scratch:
        work = Path(scratch)
        shared = _prepare(args, work)
        header = (
            f"{'path':<12} {'thr':>3} {'M items/s':>10} {'wall s':>8} {'CPU s':>8} "
            f"{'sys s':>6} {'faults':>7} "
            f"{'running':>7} {'peer M/s':>9} {'x peer':>7} {'CPU/peer':>8} {'floor M/s':>9} "
            f"{'x floor':>7} {'peak MB':>7} {'peer MB':>7} {'load':>5} output sha256"
        )
        print(header)
        for path in args.paths:
            rates: dict[int, float] = {}
            for n in counts:
                job = {
                    **shared,
                    "path": path,
                    "threads": n,
                    "repeat": args.repeat,
                    "min_seconds": args.min_seconds,
                }
                if args.where and n == counts[-1]:
                    job["few"] = max(1, n // 4)
                if args.timeline and path == "predict" and n == counts[-1]:
                    job["timeline"] = True
                result = _run_child(job)
                if "timeline" in result:
                    timelines[n] = result["timeline"]
                ours = result["ours"]
                rate = ours["items"] / ours["wall_s"]
                rates[n] = rate
                samples = {int(k): v for k, v in ours["running"].items()}
                mean = sum(k * v for k, v in samples.items()) / max(1, sum(samples.values()))
                peer = result.get("peer")
                peer_rate = peer["items"] / peer["wall_s"] if peer else None
                cpu_ratio = ours["cpu_s"] / peer["cpu_s"] if peer and peer["cpu_s"] else None
                row = {
                    "path": path,
                    "threads": n,
                    "rate": rate,
                    "mean_running": mean,
                    "peer": PEERS.get(path),
                    "peer_rate": peer_rate,
                    **{
                        key: ours[key]
                        for key in (
                            "items",
                            "wall_s",
                            "cpu_s",
                            "system_s",
                            "page_faults",
                            "running",
                            "load",
                            "few_running",
                            "runs",
                        )
                    },
                }
                floor = result.get("floor")
                floor_rate = floor["items"] / floor["wall_s"] if floor else None
                if floor:
                    row["floor_rate"] = floor_rate
                    row["floor_wall_s"] = floor["wall_s"]
                if "digest" in result:
                    row["digest"] = result["digest"]
                if "agrees_with_peer" in result:
                    row["agrees_with_peer"] = result["agrees_with_peer"]
                row["peak_bytes"] = ours["peak_bytes"]
                if peer:
                    row["peer_wall_s"] = peer["wall_s"]
                    row["peer_cpu_s"] = peer["cpu_s"]
                    row["peer_peak_bytes"] = peer.get("peak_bytes")
                peer_peak = row.get("peer_peak_bytes")
                rows.append(row)
                print(
                    f"{path:<12} {n:>3} {rate / 1e6:>10.3f} {ours['wall_s']:>8.2f} "
                    f"{ours['cpu_s']:>8.2f} {ours['system_s']:>6.2f} {ours['page_faults']:>7} "
                    f"{mean:>7.2f} "
                    f"{'' if peer_rate is None else f'{peer_rate / 1e6:9.3f}':>9} "
                    f"{'' if peer_rate is None else f'{rate / peer_rate:7.2f}':>7} "
                    f"{'' if cpu_ratio is None else f'{cpu_ratio:8.2f}':>8} "
                    f"{'' if floor_rate is None else f'{floor_rate / 1e6:9.1f}':>9} "
                    f"{'' if floor_rate is None else f'{rate / floor_rate:7.2f}':>7} "
                    f"{ours['peak_bytes'] / 2**20:>7.0f} "
                    f"{'' if peer_peak is None else f'{peer_peak / 2**20:7.0f}':>7} "
                    f"{ours['load']:>5.2f} {row.get('digest', '')}",
                    flush=True,
                )
            digests = {r["digest"] for r in rows if r["path"] == path and "digest" in r}
            if len(digests) > 1:
                print(f"{path}: the outputs differ between thread counts: {sorted(digests)}")
            speedups = {n: rates[n] / rates[counts[0]] for n in counts} if counts[0] == 1 else {}
            s = amdahl(speedups)
            two = next((r for r in rows if r["path"] == path and r["threads"] == 2), None)
            summary[path] = {
                "rates": rates,
                "speedups": speedups,
                "amdahl_serial_fraction": s,
                "predicted_speedup_16": None if s is None else 1 / (s + (1 - s) / 16),
                "predicted_rate_16": None if s is None else rates[1] / (s + (1 - s) / 16),
                "profile_serial_fraction_2": None
                if two is None
                else profile_fraction(two["running"], 2),
            }
    print("\nAmdahl fits (speed-up over 1 thread; 16-thread figures predicted from s)")
    for path, fit in summary.items():
        s, p = fit["amdahl_serial_fraction"], fit["profile_serial_fraction_2"]
        if s is None:
            continue
        print(
            f"{path:<12} s = {s:.3f} (thread samples: "
            + ("-" if p is None else f"{p:.3f}")
            + "); speed-ups "
            + ", ".join(f"{n}: {v:.2f}" for n, v in fit["speedups"].items())
            + f"; on 16 threads {fit['predicted_speedup_16']:.1f}x, "
            f"{fit['predicted_rate_16'] / 1e6:.3f} M/s"
        )
    _print_against_the_machine(summary, counts)
    if args.where:
        _print_where(rows, counts[-1])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for n, timeline in timelines.items():
        _print_timeline(timeline, n)
        (out / "bench_scaling_timeline.json").write_text(
            json.dumps({"threads": n, **timeline}) + "\n"
        )
        print(f"wrote {out / 'bench_scaling_timeline.json'}")
    report = {
        "cores": cores,
        "points": args.points,
        "threads": counts,
        "load_average_after": os.getloadavg(),
        "rows": rows,
        "summary": summary,
    }
    (out / "bench_scaling.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out / 'bench_scaling.json'}")


if __name__ == "__main__":
    main()
