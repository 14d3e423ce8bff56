"""A map over one connection finishes whatever other connections this process holds.

Each Dask client runs its own event loop. A map that followed its tasks on the loop of
the process's newest client (Dask's default) waited on one loop for what another one
reports, and could miss it for ever: the CI run that hung on the allocator test held two
clusters in one process, the test module's own and the shared one.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TypeVar

import pytest

from semantic3d.scale.cluster import ClusterSpec, DaskCluster, connect

pytestmark = pytest.mark.slow

T = TypeVar("T")


def _within(seconds: float, work: Callable[[], T]) -> T:
    """``work()`` on a thread; fails the test if it has not returned after ``seconds``."""
    outcome: list[T] = []
    errors: list[BaseException] = []

    def run() -> None:
        try:
            outcome.append(work())
        except BaseException as error:  # handed to the test's thread
            errors.append(error)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    if errors:
        raise errors[0]
    if thread.is_alive():
        pytest.fail(f"the map had not finished after {seconds:.0f} s")
    return outcome[0]


def test_a_map_finishes_while_a_newer_client_s_loop_is_busy(cluster: DaskCluster) -> None:
    started = threading.Event()
    release = threading.Event()

    def hold_the_loop() -> None:
        started.set()
        release.wait(120)

    address = cluster.client.scheduler.address
    with connect(ClusterSpec(scheduler=address, timeout_s=60)) as newer:
        newer.client.loop.add_callback(hold_the_loop)  # the newest client's loop is stuck
        assert started.wait(30)
        try:
            magnitudes = _within(30, lambda: list(cluster.map(abs, [-1, 2, -3, 4, -5])))
        finally:
            release.set()
    assert magnitudes == [1, 2, 3, 4, 5]


def test_many_maps_with_two_clients_open(cluster: DaskCluster) -> None:
    address = cluster.client.scheduler.address
    with connect(ClusterSpec(scheduler=address, timeout_s=60)) as newer:

        def both() -> list[list[int]]:
            return [list(c.map(abs, [-1, 2, -3])) for _ in range(25) for c in (cluster, newer)]

        results = _within(60, both)
    assert results == [[1, 2, 3]] * 50
