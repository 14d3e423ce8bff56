"""Real server and worker processes for the end-to-end tests (127.0.0.1 only)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import httpx

COMMAND = [sys.executable, "-m", "semantic3d.cli.server"]


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def environment(data_dir: Path, **extra: str) -> dict[str, str]:
    """The environment for a server-side process on ``data_dir``."""
    env = dict(os.environ)
    env = {k: v for k, v in env.items() if not k.startswith("SEMANTIC3D_")}
    env.update({"SEMANTIC3D_DATA_DIR": str(data_dir), "PYTHONUNBUFFERED": "1"})
    env.update(extra)
    return env


def run_command(
    args: Sequence[str], env: dict[str, str], *, input: str | None = None, timeout: float = 300
):
    """Run one ``semantic3d`` server command to completion."""
    return subprocess.run(
        [*COMMAND, *args], env=env, input=input, capture_output=True, text=True, timeout=timeout
    )


def _with_soft_open_files(command: list[str], limit: int | None) -> list[str]:
    """``command`` started with a soft open-file limit of ``limit`` (None: as it is), set by
    a shell that then becomes the command. Not a ``preexec_fn``: Python code between fork
    and exec in this threaded test process could wait for ever on a lock another thread
    held at the fork."""
    if limit is None:
        return command
    return ["/bin/sh", "-c", f'ulimit -Sn {int(limit)} && exec "$@"', "sh", *command]


class ServerProcess:
    """``semantic3d serve`` in a child process; ``url`` once it answers."""

    def __init__(
        self,
        data_dir: Path,
        log: Path,
        *args: str,
        soft_open_files: int | None = None,
        **env: str,
    ) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self._log = log.open("ab")
        serve = [*COMMAND, "serve", "--host", "127.0.0.1", "--port", str(self.port), *args]
        self.process = subprocess.Popen(
            _with_soft_open_files(serve, soft_open_files),
            env=environment(data_dir, **env),
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        self._wait_ready(log)

    def _wait_ready(self, log: Path, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"server exited with {self.process.returncode}:\n{log.read_text()}"
                )
            try:
                if httpx.get(self.url + "/api/health", timeout=1).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.kill()
        raise RuntimeError(f"server did not start in {timeout_s} s:\n{log.read_text()}")

    def stop(self) -> int:
        """SIGTERM and wait (graceful shutdown)."""
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=60)
        self._log.close()
        return code

    def kill(self) -> None:
        """SIGKILL: the crash case."""
        self.process.kill()
        self.process.wait(timeout=60)
        self._log.close()


class WorkerProcess:
    """``semantic3d worker`` in a child process."""

    def __init__(self, data_dir: Path, log: Path, **env: str) -> None:
        self._log = log.open("ab")
        self.process = subprocess.Popen(
            [*COMMAND, "worker"],
            env=environment(data_dir, **env),
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(timeout=60)
        self._log.close()

    def stop(self) -> int:
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=60)
        self._log.close()
        return code
