"""Run commands of the command line in this process while counting its computing threads.

``python tests/core/census.py '[["simulate", ...], ...]'`` runs each argument list through
the ``semantic3d`` app and prints, as JSON, how many of this process's threads were
running or ready to run (state ``R`` in ``/proc/self/task``) at each sample, taken every
2 ms by a thread of its own (not counted, nor the progress bars' refresh threads). Idle OpenMP threads must not spin for the count
to mean "computing": run it with ``OMP_WAIT_POLICY=passive``.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path


def _not_computing() -> set[int]:
    """Native ids of the progress bars' refresh threads (drawing, not computing)."""
    return {
        thread.native_id
        for thread in threading.enumerate()
        if type(thread).__name__ == "_RefreshThread" and thread.native_id is not None
    }


def _running(me: int) -> int:
    count = 0
    skip = _not_computing() | {me}
    for task in Path("/proc/self/task").iterdir():
        if int(task.name) in skip:
            continue
        try:
            data = (task / "stat").read_bytes()
        except OSError:  # the thread ended meanwhile
            continue
        end = data.rindex(b")")
        count += data[end + 2 : end + 3] == b"R"
    return count


def main() -> None:
    from semantic3d.cli.app import app

    commands = json.loads(sys.argv[1])
    samples: list[int] = []
    stop = threading.Event()

    def sample() -> None:
        me = threading.get_native_id()
        while not stop.is_set():
            samples.append(_running(me))
            time.sleep(0.002)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        for arguments in commands:
            app(arguments, standalone_mode=False)
    finally:
        stop.set()
        sampler.join()
    print(json.dumps(samples))


if __name__ == "__main__":
    main()
