"""The benchmark server under load, on 127.0.0.1, against what a user would build instead.

    python benchmarks/bench_server.py [--upload-mib 1024] [--labels 100000000]
                                      [--clients 50] [--requests 40]

Starts real ``semantic3d serve`` processes (uvicorn) on a scratch data dir and measures:

1. Upload: a ``--upload-mib`` file through the resumable chunked API (the ``submit``
   client), against a plain FastAPI ``UploadFile`` multipart endpoint (the usual way)
   in its own uvicorn process. Target >= 200 MB/s.
2. Evaluation: a ``--labels``-label submission (4 scans, deflated zip) is finalized
   (validated) and evaluated by a ``semantic3d worker`` process through the queue;
   against ``evaluate_submission`` called directly (the server's overhead). Target: well
   under a minute for 100 M labels.
3. Leaderboard: ``--clients`` concurrent keep-alive clients x ``--requests`` each on
   the JSON leaderboard (cached, and with the cache off) and the HTML page, 100 entries.
   Target: p95 < 50 ms.

Peak RSS is each server/worker process's own (``VmHWM``). Data is generated once under
benchmarks/out/server/.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from contextlib import closing
from pathlib import Path

import httpx
import numpy as np

HERE = Path(__file__).resolve()
OUT = HERE.parent / "out" / "server"
REPO = HERE.parents[1]
sys.path.insert(0, str(REPO / "tests" / "server"))
from processes import ServerProcess, WorkerProcess, free_port  # noqa: E402

CHUNK = 1 << 22
N_SCANS = 4


def peak_rss_mb(pid: int) -> float:
    """Peak resident memory of a live process (Linux ``VmHWM``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


# ----------------------------------------------------------------------------- data


def label_chunks(n: int, seed: int, *, noisy_of: int | None = None):
    """Ground truth in runs of one class (as scans are), or a 20 %-noisy prediction."""
    rng = np.random.default_rng(seed)
    truth_rng = np.random.default_rng(noisy_of) if noisy_of is not None else rng
    for start in range(0, n, CHUNK):
        size = min(CHUNK, n - start)
        truth = np.repeat(truth_rng.integers(0, 9, size // 64 + 1).astype(np.uint8), 64)[:size]
        if noisy_of is None:
            yield truth
            continue
        pred = np.where(truth == 0, 1, truth).astype(np.uint8)
        flip = rng.random(size) < 0.2
        pred[flip] = rng.integers(1, 9, int(flip.sum()), dtype=np.uint8)
        yield pred


def make_challenge(n_labels: int) -> tuple[Path, Path]:
    """``(ground-truth folder, submission zip)`` with ``n_labels`` labels in 4 scans."""
    from semantic3d.io.labels import format_labels_bytes, write_labels

    gt = OUT / f"gt-{n_labels}"
    zip_path = OUT / f"preds-{n_labels}.zip"
    if gt.is_dir() and zip_path.exists():
        return gt, zip_path
    OUT.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(gt, ignore_errors=True)
    gt.mkdir()
    per_scan = n_labels // N_SCANS
    tmp = zip_path.with_suffix(".tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for index in range(N_SCANS):
            name = f"scan{index}.labels"
            write_labels(gt / name, label_chunks(per_scan, seed=index))
            with archive.open(name, "w", force_zip64=True) as member:
                for chunk in label_chunks(per_scan, seed=100 + index, noisy_of=index):
                    member.write(format_labels_bytes(chunk))
    tmp.rename(zip_path)
    return gt, zip_path


def make_blob(mib: int) -> Path:
    path = OUT / f"blob-{mib}MiB.bin"
    if not path.exists():
        OUT.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as handle:
            for _ in range(mib):
                handle.write(os.urandom(1 << 20))
    return path


# ----------------------------------------------------------------------------- setup


def prepare_server(data_dir: Path, gt: Path) -> str:
    """Install the challenge, an account and 100 published leaderboard entries; a token."""
    import json

    from semantic3d.server.db import create_db_engine, create_session_factory, run_migrations
    from semantic3d.server.models import JOB_DONE, Job, Submission
    from semantic3d.server.services.accounts import create_token, create_user
    from semantic3d.server.services.challenges import install_challenge
    from semantic3d.server.settings import Settings

    settings = Settings(data_dir=data_dir)
    engine = create_db_engine(settings)
    run_migrations(engine)
    factory = create_session_factory(engine)
    challenge = install_challenge(factory, settings, "bench", gt)
    user = create_user(factory, "bench", "benchmark password")
    token = create_token(factory, user.id, "bench")[1]
    rng = np.random.default_rng(0)
    with factory() as session:
        for index in range(100):
            iou = rng.uniform(0.3, 0.9, 8)
            submission = Submission(
                user_id=user.id,
                challenge_id=challenge.id,
                in_flight=False,
                method_name=f"method {index}",
                description="",
                paper_url="https://example.org/paper",
                code_url="https://example.org/code",
                runtime_s=float(rng.uniform(10, 10_000)),
                hardware="1 GPU",
                filename="x.zip",
                stored_name=f"fake-{index}.zip",
                size_bytes=1,
                sha256="0" * 64,
                published=True,
                mean_iou=float(iou.mean()),
                overall_accuracy=float(rng.uniform(0.7, 0.95)),
                iou_json=json.dumps(iou.tolist()),
                n_points=1_000_000,
                result_json="{}",
            )
            session.add(submission)
            session.flush()
            session.add(Job(submission_id=submission.id, status=JOB_DONE))
        session.commit()
    engine.dispose()
    return token


# ----------------------------------------------------------------------------- 1. upload


def bench_upload(server_url: str, token: str, blob: Path) -> dict[str, float]:
    from semantic3d.server.client import BenchmarkClient, file_sha256

    size = blob.stat().st_size
    start = time.perf_counter()
    digest = file_sha256(blob)
    hash_s = time.perf_counter() - start
    with BenchmarkClient(server_url, token) as client:
        start = time.perf_counter()
        upload_id = client.upload(blob, challenge="bench", sha256=digest)
        upload_s = time.perf_counter() - start
        client._http.delete(f"/api/uploads/{upload_id}")
    return {"bytes": size, "seconds": upload_s, "hash_seconds": hash_s}


BASELINE_APP = """
import shutil, tempfile, sys
from fastapi import FastAPI, UploadFile
app = FastAPI()
@app.post("/upload")
def upload(file: UploadFile):
    with tempfile.NamedTemporaryFile(dir=sys.argv[1], delete=True) as out:
        shutil.copyfileobj(file.file, out, 8 << 20)
        return {"bytes": out.tell()}
import uvicorn
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[2]), log_level="warning")
"""


def bench_upload_baseline(blob: Path, scratch: Path) -> dict[str, float]:
    port = free_port()
    process = subprocess.Popen([sys.executable, "-c", BASELINE_APP, str(scratch), str(port)])
    try:
        url = f"http://127.0.0.1:{port}"
        for _ in range(300):
            try:
                httpx.get(url + "/docs", timeout=1)
                break
            except httpx.TransportError:
                time.sleep(0.1)
        with blob.open("rb") as handle, httpx.Client(timeout=None) as client:
            start = time.perf_counter()
            response = client.post(url + "/upload", files={"file": ("blob.bin", handle)})
            seconds = time.perf_counter() - start
        response.raise_for_status()
        rss = peak_rss_mb(process.pid)
    finally:
        process.terminate()
        process.wait()
    return {"bytes": blob.stat().st_size, "seconds": seconds, "rss": rss}


# ----------------------------------------------------------------------------- 2. evaluation


def bench_evaluation(server_url: str, token: str, data_dir: Path, preds: Path, log: Path):
    import sqlite3

    from semantic3d.evaluation import MethodInfo
    from semantic3d.server.client import BenchmarkClient

    with BenchmarkClient(server_url, token) as client:
        upload_id = client.upload(preds, challenge="bench")
        start = time.perf_counter()
        submission = client.finalize(upload_id, method=MethodInfo("bench"))
        finalize_s = time.perf_counter() - start
        worker = WorkerProcess(data_dir, log, SEMANTIC3D_WORKER_POLL_S="0.1")
        final = client.wait(submission.id, poll_s=0.2, timeout_s=600)
        rss = peak_rss_mb(worker.process.pid)
        worker.stop()
    assert final.status == "done", final
    with closing(sqlite3.connect(data_dir / "semantic3d.sqlite3")) as db:
        started, finished = db.execute(
            "SELECT started_at, finished_at FROM jobs WHERE submission_id = ?", (submission.id,)
        ).fetchone()
    from datetime import datetime

    evaluate_s = (
        datetime.fromisoformat(finished) - datetime.fromisoformat(started)
    ).total_seconds()
    return {
        "labels": final.scores.n_points if final.scores else 0,
        "finalize_s": finalize_s,
        "evaluate_s": evaluate_s,
        "worker_rss": rss,
        "mean_iou": final.scores.mean_iou if final.scores else None,
    }


def bench_direct_evaluation(gt: Path, preds: Path) -> dict[str, float]:
    code = (
        "import sys, time, resource, json; from pathlib import Path\n"
        "from semantic3d.evaluation import custom_challenge, evaluate_submission\n"
        "c = custom_challenge(Path(sys.argv[1]))\n"
        "t = time.perf_counter(); r = evaluate_submission(Path(sys.argv[2]), challenge=c)\n"
        "s = time.perf_counter() - t\n"
        "print(json.dumps({'seconds': s, 'labels': r.n_points,"
        " 'rss': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))\n"
    )
    import json

    result = subprocess.run(
        [sys.executable, "-c", code, str(gt), str(preds)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- 3. leaderboard


async def _client(host: str, port: int, path: str, n: int, latencies: list[float]) -> None:
    reader, writer = await asyncio.open_connection(host, port)
    request = f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: keep-alive\r\n\r\n".encode()
    try:
        for _ in range(n):
            start = time.perf_counter()
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            status = int(head.split(b" ", 2)[1])
            length = 0
            for line in head.split(b"\r\n"):
                if line.lower().startswith(b"content-length:"):
                    length = int(line.split(b":", 1)[1])
            await reader.readexactly(length)
            latencies.append(time.perf_counter() - start)
            if status != 200:
                raise RuntimeError(f"{path}: HTTP {status}")
    finally:
        writer.close()


async def _load(url: str, path: str, clients: int, requests: int) -> tuple[list[float], float]:
    parsed = httpx.URL(url)
    latencies: list[float] = []
    start = time.perf_counter()
    await asyncio.gather(
        *(_client(parsed.host, parsed.port, path, requests, latencies) for _ in range(clients))
    )
    return latencies, time.perf_counter() - start


def bench_leaderboard(url: str, path: str, clients: int, requests: int) -> dict[str, float]:
    asyncio.run(_load(url, path, clients, 2))  # warm up connections and caches
    latencies, seconds = asyncio.run(_load(url, path, clients, requests))
    latencies.sort()
    return {
        "n": len(latencies),
        "rps": len(latencies) / seconds,
        "p50": statistics.median(latencies) * 1000,
        "p95": latencies[int(0.95 * (len(latencies) - 1))] * 1000,
        "max": latencies[-1] * 1000,
    }


# ----------------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--upload-mib", type=int, default=1024)
    parser.add_argument("--labels", type=int, default=100_000_000)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--requests", type=int, default=40)
    args = parser.parse_args()

    print(f"preparing data under {OUT} ...", flush=True)
    gt, preds = make_challenge(args.labels)
    blob = make_blob(args.upload_mib)
    scratch = Path(tempfile.mkdtemp(prefix="semantic3d-bench-"))
    data_dir = scratch / "data"
    token = prepare_server(data_dir, gt)
    env = {
        "SEMANTIC3D_SUBMISSION_COOLDOWN_H": "0",
        "SEMANTIC3D_MAX_UPLOAD_BYTES": str(max(blob.stat().st_size, preds.stat().st_size) * 2),
    }
    try:
        server = ServerProcess(data_dir, scratch / "server.log", "--no-worker", **env)
        try:
            up = bench_upload(server.url, token, blob)
            ev = bench_evaluation(server.url, token, data_dir, preds, scratch / "worker.log")
            boards = {
                "JSON leaderboard (cached 2 s)": bench_leaderboard(
                    server.url, "/api/challenges/bench/leaderboard", args.clients, args.requests
                ),
                "HTML leaderboard page": bench_leaderboard(
                    server.url, "/challenges/bench", args.clients, args.requests
                ),
            }
            server_rss = peak_rss_mb(server.process.pid)
        finally:
            server.stop()
        uncached = ServerProcess(
            data_dir, scratch / "server2.log", "--no-worker", SEMANTIC3D_LEADERBOARD_CACHE_S="0"
        )
        try:
            boards["JSON leaderboard (no cache)"] = bench_leaderboard(
                uncached.url, "/api/challenges/bench/leaderboard", args.clients, args.requests
            )
        finally:
            uncached.stop()
        base = bench_upload_baseline(blob, scratch)
        direct = bench_direct_evaluation(gt, preds)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    mb = 1e6
    print(f"\n1. upload of {up['bytes'] / (1 << 20):.0f} MiB on loopback (target >= 200 MB/s)")
    print(f"{'contender':<44} {'MB/s':>8} {'seconds':>8} {'server peak RSS MB':>19}")
    print(
        f"{'semantic3d chunked upload (64 MiB PUTs)':<44} {up['bytes'] / up['seconds'] / mb:>8.0f} "
        f"{up['seconds']:>8.2f} {server_rss:>19.0f}"
    )
    print(
        f"{'FastAPI UploadFile multipart (one POST)':<44} "
        f"{base['bytes'] / base['seconds'] / mb:>8.0f} {base['seconds']:>8.2f} {base['rss']:>19.0f}"
    )
    print(f"  client-side sha256 first: {up['hash_seconds']:.2f} s")

    print(
        f"\n2. evaluation of {args.labels:,} labels, {ev['labels']:,} of them labelled "
        "(target: well under a minute)"
    )
    print(f"{'contender':<44} {'M labels/s':>10} {'seconds':>8} {'peak RSS MB':>12}")
    labels_total = args.labels
    print(
        f"{'server: worker process via the queue':<44} {labels_total / ev['evaluate_s'] / 1e6:>10.1f} "
        f"{ev['evaluate_s']:>8.2f} {ev['worker_rss']:>12.0f}"
    )
    print(
        f"{'evaluate_submission called directly':<44} "
        f"{labels_total / direct['seconds'] / 1e6:>10.1f} {direct['seconds']:>8.2f} "
        f"{direct['rss']:>12.0f}"
    )
    print(f"  finalize (validation of every label, then queue): {ev['finalize_s']:.2f} s")
    print(f"  mIoU {ev['mean_iou']:.4f}")

    print(
        f"\n3. leaderboard, {args.clients} concurrent clients x {args.requests} requests, "
        "100 entries (target p95 < 50 ms)"
    )
    print(f"{'endpoint':<34} {'req/s':>8} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8}")
    for name, row in boards.items():
        print(
            f"{name:<34} {row['rps']:>8.0f} {row['p50']:>8.1f} {row['p95']:>8.1f} {row['max']:>8.1f}"
        )
    print(f"\nmachine: {os.cpu_count()} CPUs; server and clients share them")


if __name__ == "__main__":
    main()
