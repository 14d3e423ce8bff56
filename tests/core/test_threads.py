"""The thread budget: its sources, the thread map and read-ahead built on it, and the cap
of ``--threads`` as the command line honours it (threads counted while commands run)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from semantic3d.core import threads
from semantic3d.core.threads import (
    apportion_threads,
    iter_ahead,
    map_in_threads,
    numba_threads,
    set_thread_limit,
    take_free_threads,
    thread_budget,
    thread_limit,
)

ROOT = Path(__file__).resolve().parents[2]


def test_the_budget_is_the_limit_else_the_environment_else_the_cores(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert thread_budget() == threads.available_cores()
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.setenv("NUMBA_NUM_THREADS", "5")
    assert thread_budget() == 3
    with thread_limit(7) as budget:
        assert budget == thread_budget() == 7
        assert os.environ["OMP_NUM_THREADS"] == "7"
    assert thread_budget() == 3
    assert os.environ["OMP_NUM_THREADS"] == "3"
    with pytest.raises(ValueError, match="expected at least 1, found 0"):
        set_thread_limit(0)


def test_a_task_sees_its_share_of_the_budget() -> None:
    with thread_limit(4), numba_threads(2) as count:
        assert thread_budget() == 2
        assert count >= 1
    seen = list(map_in_threads(lambda _: thread_budget(), range(3), n_threads=4))
    assert seen == [1, 1, 1]


def test_the_map_keeps_order_or_completion_and_raises_the_first_error() -> None:
    def slow_square(x: int) -> int:
        time.sleep(0.001 * (7 - x % 7))
        return x * x

    assert list(map_in_threads(slow_square, range(20), n_threads=3)) == [x * x for x in range(20)]
    unordered = list(map_in_threads(slow_square, range(20), n_threads=3, ordered=False))
    assert sorted(unordered) == [x * x for x in range(20)]

    def fail_at_five(x: int) -> int:
        if x >= 5:
            raise ValueError(f"item {x}")
        return x

    with pytest.raises(ValueError, match="item 5"):
        list(map_in_threads(fail_at_five, range(20), n_threads=3))


def test_tasks_running_at_once_never_hold_more_threads_than_the_map() -> None:
    lock = threading.Lock()
    running = [0, 0]  # now, most

    def task(item: int) -> int:
        with lock:
            running[0] += 3
            running[1] = max(running[1], running[0])
        time.sleep(0.005)
        with lock:
            running[0] -= 3
        return item

    done = list(map_in_threads(task, range(12), n_threads=4, numba_threads_per_task=3))
    assert done == list(range(12))
    assert running[1] == 3  # one task of 3 threads at a time on a map of 4


def test_the_last_tasks_take_the_threads_the_others_gave_back() -> None:
    """While tasks wait for their turn no task takes more; once every task has started,
    a task asking takes a share of the free threads (its budget and numba's count grow);
    the threads held at once never exceed the map's."""
    import numba

    lock = threading.Lock()
    held = [0, 0]  # now, most
    grown: dict[int, tuple[int, int]] = {}
    asked = threading.Event()  # the long task asked before any other task ended
    quick_done = threading.Event()
    ended = [0]

    def hold(count: int) -> None:
        with lock:
            held[0] += count
            held[1] = max(held[1], held[0])

    def task(item: int) -> int:
        hold(thread_budget())
        if item == 0:  # the long task: asks while others wait, then after they all ended
            early = take_free_threads()
            asked.set()
            quick_done.wait(10)
            time.sleep(0.05)
            late = take_free_threads()
            hold(late - early)
            grown[item] = (early, late)
            assert thread_budget() == late
            assert numba.get_num_threads() == min(late, numba.config.NUMBA_NUM_THREADS)
        else:
            asked.wait(10)
            time.sleep(0.002)
        with lock:
            held[0] -= thread_budget()
            if item:
                ended[0] += 1
                if ended[0] == 5:
                    quick_done.set()
        return item

    with thread_limit(4):
        done = list(map_in_threads(task, range(6), n_threads=4, ordered=False))
    assert sorted(done) == list(range(6))
    assert grown[0] == (1, 4)  # 1 while tasks were to start; all 4 once they had ended
    assert held == [0, 4]
    assert take_free_threads() == thread_budget()  # outside a map: the budget


@pytest.mark.parametrize("ordered", [True, False])
def test_a_nested_maps_tail_lends_its_idle_threads_to_the_enclosing_map(ordered: bool) -> None:
    """A task of 3 threads maps a long item and two short ones: once the short ones have
    ended, it keeps one thread and the next task (of 2) starts before the long item ends;
    afterwards the task takes its threads back as far as they are free."""
    long_started, b_started = threading.Event(), threading.Event()
    seen: dict[str, object] = {}

    def inner(item: int) -> int:
        if item == 0:
            long_started.set()
            seen["b started during the long item"] = b_started.wait(10)
        return item

    def outer(name: str) -> str:
        if name == "a":
            results = list(map_in_threads(inner, range(3), ordered=ordered))
            seen["a"] = (results if ordered else sorted(results), thread_budget())
        else:
            b_started.set()
            seen["b budget"] = thread_budget()
        return name

    shares = {"a": 3, "b": 2}
    with thread_limit(4):
        done = list(map_in_threads(outer, "ab", numba_threads_per_task=shares.__getitem__))
    assert done == ["a", "b"]
    assert seen["b started during the long item"] is True
    assert seen["b budget"] == 2
    assert seen["a"] == ([0, 1, 2], 3)  # its threads back once the map ended


def test_a_nested_map_told_not_to_lend_keeps_its_threads_through_its_tail() -> None:
    """With ``lend_tail=False`` the task of 3 threads keeps them while its long item runs
    alone: the next task (of 2) starts only once the nested map has ended."""
    long_done = threading.Event()
    seen: dict[str, object] = {}

    def inner(item: int) -> int:
        if item == 0:
            time.sleep(0.1)
            long_done.set()
        return item

    def outer(name: str) -> str:
        if name == "a":
            assert list(map_in_threads(inner, range(3), lend_tail=False)) == [0, 1, 2]
            seen["a budget"] = thread_budget()
        else:
            seen["b started after the long item"] = long_done.is_set()
        return name

    shares = {"a": 3, "b": 2}
    with thread_limit(4):
        done = list(map_in_threads(outer, "ab", numba_threads_per_task=shares.__getitem__))
    assert done == ["a", "b"]
    assert seen == {"b started after the long item": True, "a budget": 3}


def _growing(threads_of: dict[str, int], n_items: int) -> dict[str, object]:
    """Map tasks "big" and "small" on a map of their shares' sum; "big" maps ``n_items``
    items of one thread each, which wait for "small" to end and then overlap a while.
    Returns the most items of "big" running at once, the most threads held at once
    (big's items plus small's share) and big's budget after its nested map."""
    lock = threading.Lock()
    state = {"items": 0, "most items": 0, "held": 0, "most held": 0}
    started = threading.Event()  # big's first items are running
    small_done = threading.Event()

    def add(key: str, count: int) -> None:
        with lock:
            state[key] += count
            state[f"most {key}"] = max(state[f"most {key}"], state[key])

    def item(number: int) -> int:
        add("items", 1)
        add("held", 1)
        started.set()
        small_done.wait(10)
        time.sleep(0.03)
        add("items", -1)
        add("held", -1)
        return number

    def task(name: str) -> str:
        if name == "small":
            add("held", thread_budget())
            started.wait(10)
            time.sleep(0.02)
            add("held", -thread_budget())
            small_done.set()
        else:
            assert sorted(map_in_threads(item, range(n_items), ordered=False)) == list(
                range(n_items)
            )
            state["budget after"] = thread_budget()
        return name

    with thread_limit(sum(threads_of.values())):
        done = list(map_in_threads(task, ["big", "small"], numba_threads_per_task=threads_of.get))
    assert done == ["big", "small"]
    return state


def test_a_nested_map_grows_with_the_threads_the_enclosing_maps_ended_tasks_left() -> None:
    """A task of 3 threads maps 12 items of one thread: once the other task (1 thread) has
    ended, its thread joins them (4 at once), never more than the map's 4 threads in all;
    the task keeps it after its nested map."""
    state = _growing({"big": 3, "small": 1}, 12)
    assert state["most items"] == 4
    assert state["most held"] <= 4
    assert state["budget after"] == 4


def test_a_nested_map_of_a_one_thread_task_grows_too() -> None:
    """On one thread, inside a map's task, the nested map still runs on a pool: when the
    other task ends, the two threads run its items (never more than the map's two)."""
    state = _growing({"big": 1, "small": 1}, 6)
    assert state["most items"] == 2
    assert state["most held"] <= 2


def test_a_nested_map_does_not_grow_while_the_enclosing_map_has_tasks_to_start() -> None:
    """The map's third task waits for the threads of the first two: the nested map of the
    first does not take the second's thread before the third has started."""
    lock = threading.Lock()
    most = [0, 0]
    third_started = threading.Event()
    second_done = threading.Event()

    def item(number: int) -> int:
        with lock:
            most[0] += 1
            most[1] = max(most[1], most[0])
        second_done.wait(10)
        time.sleep(0.02)
        with lock:
            most[0] -= 1
        return number

    def task(name: str) -> str:
        if name == "first":
            list(map_in_threads(item, range(8)))
        elif name == "second":
            time.sleep(0.05)
            second_done.set()
        else:
            third_started.set()
            time.sleep(0.2)  # holds its 2 threads while the first's items run
        return name

    shares = {"first": 2, "second": 1, "third": 2}
    with thread_limit(4):
        done = list(
            map_in_threads(task, ["first", "second", "third"], numba_threads_per_task=shares.get)
        )
    assert done == ["first", "second", "third"]
    assert third_started.is_set()
    assert most[1] == 2  # the second's thread went to the third, not to the first's items


def test_a_nested_map_outside_a_task_keeps_its_threads() -> None:
    with thread_limit(3):
        assert list(map_in_threads(lambda item: thread_budget(), range(4))) == [1, 1, 1, 1]
        assert thread_budget() == 3


def test_read_ahead_gives_the_items_in_order_and_stops_with_the_consumer() -> None:
    produced: list[int] = []

    def items() -> object:
        for x in range(100):
            produced.append(x)
            yield x

    with thread_limit(2):
        assert list(iter_ahead(range(50))) == list(range(50))
        ahead = iter_ahead(items(), depth=2)
        assert [next(ahead) for _ in range(3)] == [0, 1, 2]
        ahead.close()  # type: ignore[attr-defined]
    assert len(produced) < 100

    def broken() -> object:
        yield 1
        raise OSError("disk gone")

    with thread_limit(2), pytest.raises(OSError, match="disk gone"):
        list(iter_ahead(broken()))


def test_one_thread_starts_no_thread() -> None:
    before = threading.active_count()
    seen: list[int] = []
    with thread_limit(1):
        for _ in iter_ahead(range(5)):
            seen.append(threading.active_count())
        results = list(map_in_threads(lambda x: threading.active_count(), range(5)))
    assert seen == [before] * 5
    assert results == [before] * 5


_CONFIG = """
[features]
base_voxel_size_m = 0.1
n_levels = 6
[forest]
n_estimators = 10
max_depth = 10
[sampling]
points_per_class = 300
[prediction]
tile_size_m = 6.4
max_points_in_memory = 0
chunk_size = 20000
"""


def _census(commands: list[list[str]], tmp_path: Path) -> Counter[int]:
    env = {
        key: value for key, value in os.environ.items() if key not in threads.ENVIRONMENT_VARIABLES
    }
    env.update(PYTHONPATH=str(ROOT / "src"), OMP_WAIT_POLICY="passive")
    result = subprocess.run(
        [sys.executable, str(Path(__file__).with_name("census.py")), json.dumps(commands)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        stdin=subprocess.DEVNULL,
        check=True,
        timeout=600,
    )
    return Counter(json.loads(result.stdout.strip().splitlines()[-1]))


def _within(counts: Counter[int], cap: int) -> None:
    """Threads running at once stay within ``cap``: on average, and but for one sample in
    ten (the thread that hands work out and takes results back wakes between tasks)."""
    total = sum(counts.values())
    assert total > 100, counts
    assert sum(n for running, n in counts.items() if running > cap) < total / 10, counts
    assert sum(running * n for running, n in counts.items()) / total <= cap + 0.05, counts


@pytest.mark.slow
def test_threads_computing_at_once_stay_within_the_cap(tmp_path: Path) -> None:
    """simulate, train, predict (tiled) and evaluate with --threads 1, then predict with
    --threads 2: the process's threads running or ready to run, sampled every 2 ms."""
    (tmp_path / "config.toml").write_text(_CONFIG)
    commands = [
        ["simulate", "--scene", "street", "--points", "80000", "--out", "scans"],
        # two scans: a folder's scans are labelled side by side, within the cap too
        ["simulate", "--scene", "village", "--stations", "2", "--points", "30000", "--out", "more"],
        ["baseline", "covariance", "train", "--data", "scans", "--out", "model.s3dm"],
        ["baseline", "covariance", "predict", "--model", "model.s3dm", "--data", "more"],
        ["evaluate", "--gt", "more", "--pred", "predictions"],
    ]
    commands[2] += ["--config", "config.toml"]
    _within(_census([[*command, "--threads", "1"] for command in commands], tmp_path), 1)
    predict = [*commands[3], "--out", "again", "--threads", "2"]
    counts = _census([predict], tmp_path)
    _within(counts, 2)
    assert counts[2] > 0  # and two threads do compute at once


@given(
    st.lists(st.floats(0.0, 1e6, allow_nan=False), min_size=1, max_size=40),
    st.integers(1, 64),
)
def test_apportioned_threads_follow_the_work_and_never_overfill_the_map(
    work: list[float], n_threads: int
) -> None:
    shares = apportion_threads(dict(enumerate(work)), n_threads)
    assert sorted(shares) == list(range(len(work)))
    assert all(share >= 1 for share in shares.values())
    total = sum(work)
    if total <= 0:
        assert set(shares.values()) == {1}
        return
    quota = {key: n_threads * w / total for key, w in enumerate(work)}
    large = [key for key in quota if quota[key] >= 1.0]
    small_quota = sum(q for q in quota.values() if q < 1.0)
    taken = sum(shares[key] for key in large)
    if small_quota >= 1.0:  # the small ones keep the whole seats of their summed share
        assert n_threads - taken in (math.floor(small_quota), math.floor(small_quota) + 1)
        scale = 1.0
    else:  # they follow the large ones, which share every seat
        assert taken == (n_threads if large else 0)
        scale = n_threads / (n_threads - small_quota)
    for key in large:  # a share's whole threads, or one more
        assert math.floor(quota[key]) <= shares[key] <= math.floor(quota[key] * scale) + 1
    for key in quota:
        if quota[key] < 1.0:
            assert shares[key] == 1
    for a in quota:  # more work, never fewer threads
        for b in quota:
            if work[a] > work[b]:
                assert shares[a] >= shares[b]


def test_apportioned_threads_leave_seats_to_many_small_tasks() -> None:
    """Four tasks of a quarter of the work each on 16 threads get 4 each; one task with
    60 % beside forty of 1 % each gets 10 of 16 (its 9.6, rounded by the larger remainder
    of itself, 0.6, against the small ones' 6.4), and the small ones run on the other 6;
    a task with 60 % on 2 threads, beside small ones of less than a thread together, gets
    both (they follow it)."""
    assert apportion_threads({k: 1.0 for k in "abcd"}, 16) == dict.fromkeys("abcd", 4)
    work = {"large": 60.0, **{f"small{i}": 1.0 for i in range(40)}}
    shares = apportion_threads(work, 16)
    assert shares["large"] == 10
    assert {shares[f"small{i}"] for i in range(40)} == {1}
    assert apportion_threads({"only": 5.0}, 8) == {"only": 8}
    assert apportion_threads({"large": 60.0, "a": 20.0, "b": 20.0}, 2) == {
        "large": 2,
        "a": 1,
        "b": 1,
    }
