"""Fixtures for the dataset tests: a local HTTP mirror of the benchmark and 7z archive builders.

The mirror serves archives the tests build with py7zr from small generated scan files, at
the registry's own archive paths, so downloads run exactly as against semantic3d.net.
"""

from __future__ import annotations

import io
import re
import socket
import threading
import zlib
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlparse

import numpy as np
import py7zr
import pytest

from semantic3d.datasets.registry import ScanInfo, scans

DATA_PREFIX = "/data/"


def scan_text(name: str, n_points: int = 200) -> bytes:
    """A small deterministic ASCII scan (``x y z intensity r g b`` lines) for ``name``."""
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    xyz = rng.uniform(-50.0, 50.0, size=(n_points, 3))
    intensity = rng.integers(-2048, 2047, size=n_points)
    rgb = rng.integers(0, 256, size=(n_points, 3))
    lines = [
        f"{x:.3f} {y:.3f} {z:.3f} {i} {r} {g} {b}"
        for (x, y, z), i, (r, g, b) in zip(xyz, intensity, rgb, strict=True)
    ]
    return ("\n".join(lines) + "\n").encode()


def labels_text(name: str, n_points: int = 200) -> bytes:
    """A small deterministic ``.labels`` file (one value 0..8 per line) for ``name``."""
    rng = np.random.default_rng(zlib.crc32(name.encode()) + 1)
    return ("\n".join(str(v) for v in rng.integers(0, 9, size=n_points)) + "\n").encode()


def build_7z(members: Mapping[str, bytes]) -> bytes:
    """A 7z archive (bytes) holding ``members`` (name -> content)."""
    buffer = io.BytesIO()
    with py7zr.SevenZipFile(buffer, mode="w") as archive:
        for name, data in members.items():
            archive.writestr(data, name)
    return buffer.getvalue()


def build_hostile_7z(members: Mapping[str, bytes]) -> bytes:
    """Like :func:`build_7z` but allows names py7zr refuses to write (``../x``, ``/abs``)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(py7zr.py7zr, "check_archive_path", lambda _name: True)
        return build_7z(members)


@dataclass(frozen=True)
class BenchmarkFiles:
    """Generated content of every scan file, and the archives that pack them."""

    contents: dict[str, bytes]  # local file name -> bytes
    archives: dict[str, bytes]  # archive path relative to the data root -> 7z bytes


def _build_benchmark(selected: tuple[ScanInfo, ...]) -> BenchmarkFiles:
    contents: dict[str, bytes] = {}
    packed: dict[str, dict[str, bytes]] = defaultdict(dict)
    for info in selected:
        contents[info.points.filename] = scan_text(info.name)
        packed[info.points.archive][info.points.member] = contents[info.points.filename]
        if info.labels is not None:
            contents[info.labels.filename] = labels_text(info.name)
            packed[info.labels.archive][info.labels.member] = contents[info.labels.filename]
    return BenchmarkFiles(
        contents=contents,
        archives={path: build_7z(members) for path, members in packed.items()},
    )


@pytest.fixture(scope="session")
def benchmark_files() -> BenchmarkFiles:
    """Small stand-ins for all 34 scans, packed as the benchmark packs them."""
    return _build_benchmark(scans())


@dataclass(frozen=True)
class SeenRequest:
    path: str
    range: str | None


@dataclass
class Mirror:
    """A local stand-in for the benchmark's web server.

    ``files`` maps URL paths to bodies; ``script`` maps a URL path to the behaviours of its
    next requests, consumed one per request: ``"cut"`` (send half the body, then drop the
    connection), ``"drop"`` (send headers, then drop), ``"503"``, ``"404"``, ``"full"``
    (answer 200 with the whole body even to a range request). Unscripted requests are
    served normally, honouring ``Range``. ``always`` applies a behaviour to every request.
    """

    base_url: str = ""
    files: dict[str, bytes] = field(default_factory=dict)
    script: dict[str, list[str]] = field(default_factory=dict)
    always: dict[str, str] = field(default_factory=dict)
    requests: list[SeenRequest] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def url_path(self, archive: str) -> str:
        return DATA_PREFIX + archive

    def publish(self, archives: Mapping[str, bytes]) -> None:
        for archive, data in archives.items():
            self.files[self.url_path(archive)] = data

    def next_action(self, path: str) -> str:
        with self.lock:
            if path in self.always:
                return self.always[path]
            queue = self.script.get(path)
            return queue.pop(0) if queue else "serve"

    def requests_for(self, archive: str) -> list[SeenRequest]:
        return [seen for seen in self.requests if seen.path == self.url_path(archive)]


def _make_handler(mirror: Mirror) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args: object) -> None:
            pass  # keep test output clean

        def do_GET(self) -> None:
            path = urlparse(self.path).path
            range_header = self.headers.get("Range")
            with mirror.lock:
                mirror.requests.append(SeenRequest(path, range_header))
            action = mirror.next_action(path)
            data = mirror.files.get(path)
            if data is None or action == "404":
                self.send_error(404, "Not Found")
                return
            if action == "503":
                self.send_error(503, "Service Unavailable")
                return
            start = 0
            match = re.fullmatch(r"bytes=(\d+)-", range_header or "")
            if match and action != "full":
                start = int(match.group(1))
                if start >= len(data):
                    self.send_response(416)
                    self.send_header("Content-Range", f"bytes */{len(data)}")
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                self.send_response(206)
                self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
            else:
                self.send_response(200)
            body = data[start:]
            self.send_header("Content-Type", "application/x-7z-compressed")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            if action == "cut":
                self.wfile.write(body[: len(body) // 2])
            if action in ("cut", "drop"):
                self.wfile.flush()
                self.close_connection = True
                self.connection.shutdown(socket.SHUT_RDWR)
                return
            self.wfile.write(body)

    return Handler


@pytest.fixture
def mirror() -> Iterator[Mirror]:
    """A local HTTP server on 127.0.0.1 (its own port), serving nothing until published to."""
    state = Mirror()
    server = ThreadingHTTPServer(("127.0.0.1", 0), _make_handler(state))
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    host, port = server.server_address[:2]
    state.base_url = f"http://{host}:{port}{DATA_PREFIX}"
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)


@pytest.fixture
def full_mirror(mirror: Mirror, benchmark_files: BenchmarkFiles) -> Mirror:
    """The mirror publishing every archive of the benchmark."""
    mirror.publish(benchmark_files.archives)
    return mirror


class ArchiveTools:
    """The archive and content builders, handed to tests through the ``tools`` fixture."""

    build_7z = staticmethod(build_7z)
    build_hostile_7z = staticmethod(build_hostile_7z)
    scan_text = staticmethod(scan_text)
    labels_text = staticmethod(labels_text)


@pytest.fixture(scope="session")
def tools() -> type[ArchiveTools]:
    """Builders for 7z archives (benign and hostile) and generated scan contents."""
    return ArchiveTools
