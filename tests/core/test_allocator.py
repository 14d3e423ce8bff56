"""The allocator policy of compute commands: freed memory is reused, not faulted in again."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

_GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

_FAULTS = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from semantic3d.core.allocator import keep_freed_memory
    assert keep_freed_memory() and keep_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
counts = []
for _ in range(4):  # a tile's arrays, made, written and freed, tile after tile
    before = faults()
    blocks = [np.ones(100_000 // 8) for _ in range(200)]  # 20 MB in blocks of 100 kB
    del blocks
    counts.append(faults() - before)
print(min(counts[1:]))
"""


def _faults(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True
    )
    return int(done.stdout.strip())


@pytest.mark.skipif(not _GLIBC, reason="the policy is glibc's")
def test_kept_memory_is_reused_without_page_faults() -> None:
    """By default the 20 MB freed at the top of the heap go back to the kernel and every
    page faults in again for the next tile; kept, the next tile reuses them."""
    assert _faults("default") > 1000
    assert _faults("keep") < 100


@pytest.mark.skipif(not _GLIBC, reason="the policy is glibc's")
def test_a_compute_command_keeps_freed_memory() -> None:
    """The ``--threads`` option of compute commands applies the policy as it is parsed."""
    code = (
        "import semantic3d.core.allocator as a\n"
        "from typer.testing import CliRunner\n"
        "from semantic3d.cli.app import app\n"
        "assert a._applied is None\n"
        "CliRunner().invoke(app, ['simulate', '--help'])\n"
        "assert a._applied is None, 'help computes nothing'\n"
        "result = CliRunner().invoke(app, ['evaluate', 'nowhere', 'nothing', '--threads', '1'])\n"
        "print(a._applied)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip().splitlines()[-1] == "True"


def test_elsewhere_nothing_is_changed(monkeypatch: pytest.MonkeyPatch) -> None:
    import semantic3d.core.allocator as allocator

    monkeypatch.setattr(allocator, "_applied", None)
    monkeypatch.setattr(allocator.platform, "libc_ver", lambda: ("musl", "1.2"))
    assert allocator.keep_freed_memory() is False
    assert allocator.keep_freed_memory() is False  # answered once a process


_ARENAS = """
import ctypes, os, sys, tempfile, threading
import numpy as np
if sys.argv[1] == "keep":
    from semantic3d.core.allocator import keep_freed_memory
    assert keep_freed_memory()
held, ready = [], threading.Barrier(8)
def work():
    held.append(np.ones(1 << 17))  # 1 MiB from this thread's arena
    ready.wait()
threads = [threading.Thread(target=work) for _ in range(8)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
libc = ctypes.CDLL(None)
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
with tempfile.TemporaryDirectory() as folder:
    path = os.path.join(folder, "info.xml")
    stream = libc.fopen(path.encode(), b"w")
    assert libc.malloc_info(0, stream) == 0
    libc.fclose(stream)
    print(open(path).read().count("<heap nr="))
"""


def _arenas(mode: str, **environment: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", _ARENAS, mode],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, **environment},
    )
    return int(done.stdout.strip())


@pytest.mark.skipif(not _GLIBC, reason="the policy is glibc's")
def test_threads_share_a_few_arenas() -> None:
    """Eight threads allocating at once get heaps of their own by default; under the
    policy they share :func:`arena_limit`'s, so one thread's freed memory serves the next."""
    from semantic3d.core.allocator import arena_limit
    from semantic3d.core.threads import available_cores

    assert _arenas("default") > arena_limit(available_cores())
    assert _arenas("keep") == arena_limit(available_cores())


@pytest.mark.skipif(not _GLIBC, reason="the policy is glibc's")
def test_the_users_arena_limit_is_kept() -> None:
    assert _arenas("keep", MALLOC_ARENA_MAX="5") == 5
    assert _arenas("keep", GLIBC_TUNABLES="glibc.malloc.arena_max=4") == 4


def test_a_few_arenas_for_every_machine() -> None:
    from semantic3d.core.allocator import MIN_ARENAS, arena_limit

    limits = [arena_limit(cores) for cores in (1, 2, 16, 23, 24, 64, 256)]
    assert limits == [MIN_ARENAS] * 4 + [3, 8, 32]
