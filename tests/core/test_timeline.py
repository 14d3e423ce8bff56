"""The timeline of a job's steps: spans recorded only while asked, on every thread."""

from __future__ import annotations

import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from semantic3d.core.timeline import recording, span


def _busy(seconds: float) -> None:
    until = time.thread_time() + seconds
    while time.thread_time() < until:
        pass


def test_nothing_is_recorded_outside_a_recording() -> None:
    with span("before") as attrs:
        attrs["rows"] = 3
    with recording() as timeline:
        pass
    with span("after"):
        pass
    assert timeline.spans == []
    assert timeline.end_s is not None and timeline.end_s >= 0


def test_spans_nest_on_their_thread_and_carry_what_the_block_adds() -> None:
    with recording() as timeline, span("tile", tile=[1, 2]) as tile:
        with span("features"):
            _busy(0.02)
        with span("forest", rows=10) as forest:
            forest["classes"] = 8
        tile["done"] = True
    by_name = {s.name: s for s in timeline.spans}
    assert [s.name for s in timeline.spans] == ["tile", "features", "forest"]
    outer = by_name["tile"]
    assert outer.parent == -1 and outer.attrs == {"tile": [1, 2], "done": True}
    assert by_name["features"].parent == by_name["forest"].parent == outer.number
    assert by_name["forest"].attrs == {"rows": 10, "classes": 8}
    assert by_name["features"].cpu_s >= 0.015
    assert outer.start_s <= by_name["features"].start_s <= by_name["features"].end_s
    assert by_name["forest"].end_s <= outer.end_s <= timeline.end_s  # type: ignore[operator]
    assert by_name["features"].end_s <= by_name["forest"].start_s
    json.dumps([s.to_dict() for s in timeline.spans])  # JSON-ready


def test_spans_of_every_thread_are_kept_with_their_own_parents_and_cpu() -> None:
    def work(number: int) -> None:
        with span("tile", number=number), span("cut square"):
            _busy(0.01 * (number + 1))

    with recording() as timeline, ThreadPoolExecutor(4, thread_name_prefix="worker") as pool:
        list(pool.map(work, range(8)))
    tiles = timeline.named("tile")
    squares = timeline.named("cut square")
    assert sorted(s.attrs["number"] for s in tiles) == list(range(8))
    assert len(squares) == 8
    numbers = {s.number: s for s in tiles}
    for square in squares:
        parent = numbers[square.parent]  # the tile of its own thread, never another's
        assert parent.thread == square.thread and parent.thread.startswith("worker")
        assert parent.start_s <= square.start_s <= square.end_s <= parent.end_s
        assert square.cpu_s >= 0.009 * (parent.attrs["number"] + 1)
    assert len({s.number for s in timeline.spans}) == 16


def test_the_tasks_of_a_thread_map_stay_under_the_step_that_mapped_them() -> None:
    """Spans begun in a map's tasks (other threads) have the caller's open span as their
    parent; a span begun outside, on a plain thread, has none; the caller's own spans
    nest as before."""
    from semantic3d.core.threads import map_in_threads, thread_limit
    from semantic3d.core.timeline import inside, open_span

    two = threading.Barrier(2)  # the first two tasks run at once, on two threads

    def square(number: int) -> int:
        with span("cut square", number=number):
            if number < 2:
                two.wait(10)
            _busy(0.002)
        return threading.get_ident()

    with recording() as timeline, thread_limit(3):
        with span("cut") as cut:
            cut["threads"] = len(set(map_in_threads(square, range(6), ordered=False)))
            assert open_span() != -1
        stray = threading.Thread(target=square, args=(9,))
        stray.start()
        stray.join()
        with inside(-1), span("after"):
            pass
    (cut_span,) = timeline.named("cut")
    squares = timeline.named("cut square")
    assert cut_span.attrs["threads"] > 1
    assert sorted(s.attrs["number"] for s in squares) == [0, 1, 2, 3, 4, 5, 9]
    for step in squares:
        assert step.parent == (-1 if step.attrs["number"] == 9 else cut_span.number)
        assert step.thread != cut_span.thread or step.attrs["number"] == 9
    assert timeline.named("after")[0].parent == -1
    assert open_span() == -1  # no recording open


def test_a_span_that_raises_is_kept_and_the_error_passes() -> None:
    with recording() as timeline:
        with pytest.raises(ValueError, match="bad tile"), span("tile"):
            raise ValueError("bad tile")
        with span("next"):
            pass
    assert [(s.name, s.parent) for s in timeline.spans] == [("tile", -1), ("next", -1)]


def test_one_recording_at_a_time() -> None:
    with recording(), pytest.raises(RuntimeError, match="already being recorded"), recording():
        pass
    with recording() as again, span("x"):  # the first one ended: a new one may start
        pass
    assert [s.name for s in again.spans] == ["x"]


def test_spans_still_open_when_the_recording_ends_are_not_recorded_by_the_next() -> None:
    started = threading.Event()
    release = threading.Event()

    def late() -> None:
        with span("late"):
            started.set()
            release.wait(5)

    with recording() as first:
        thread = threading.Thread(target=late)
        thread.start()
        started.wait(5)
    with recording() as second:
        release.set()
        thread.join(5)
    assert [s.name for s in first.spans] == []
    # the span began in the first recording: it ends into that one, never the second
    assert [s.name for s in second.spans] == []
