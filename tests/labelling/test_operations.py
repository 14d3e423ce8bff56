"""Compiled operations equal plain numpy references; deltas, progress, cancel, fits, stats."""

from __future__ import annotations

import io
import threading
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.labelling import geometry
from semantic3d.labelling.delta import Delta
from semantic3d.labelling.errors import OperationCancelledError, OperationError
from semantic3d.labelling.fitting import Region
from semantic3d.labelling.opening import open_label_session
from semantic3d.labelling.stats import selection_stats

from .conftest import NODE_CAPACITY

TOP_VIEW = np.diag([0.02, 0.02, -0.001, 1.0])
TRIANGLE = [(-0.3, -0.3), (0.35, -0.2), (0.0, 0.4)]


@pytest.fixture
def session(simulated_scan, tmp_path):
    prediction = simulated_scan.truth.copy()
    prediction[::7] = (prediction[::7] % 8) + 1
    pred_path = tmp_path / "pred.labels"
    pred_path.write_text("".join(f"{v}\n" for v in prediction))
    opened = open_label_session(
        simulated_scan.cache.path,
        labels_path=tmp_path / "ops.labels",
        prediction_path=pred_path,
        node_capacity=NODE_CAPACITY,
    )
    yield opened
    opened.close()


def _local(session) -> np.ndarray:
    return np.asarray(session.scan.xyz) - session.origin


def test_compiled_operations_equal_numpy_references(session, simulated_scan) -> None:
    xyz = _local(session)
    labels = simulated_scan.truth.copy()
    session.labels[:] = labels  # a labelled scan, for locks and layers
    session.set_layer(3, locked=True)
    session.set_layer(4, hidden=True)
    editable = ~(session.hidden | session.locked)[labels]

    inside = geometry.points_in_polygon(geometry.project_to_ndc(xyz, TOP_VIEW)[0], TRIANGLE)
    session.split(TOP_VIEW, TRIANGLE, keep="outside")
    expected = np.ones(labels.size, bool)
    expected[editable] = ~inside[editable]
    np.testing.assert_array_equal(session.working, expected)

    session.reset(scope="unlabelled")
    np.testing.assert_array_equal(session.working, editable & (labels == 0))
    session.reset()
    np.testing.assert_array_equal(session.working, editable)

    region = Region.sphere(xyz[labels == 5].mean(axis=0), 12.0)
    model = {"kind": "plane", "point": xyz[labels == 5][0].tolist(), "normal": [1.0, 0.0, 0.0]}
    seeds = [xyz[labels == 5][0].tolist()]
    session.fit("plane", seeds, tolerance_m=0.5, region=region, model=model)
    plane = geometry.PlaneModel(np.array(model["point"]), np.array(model["normal"]))
    in_region = np.linalg.norm(xyz - region.centre, axis=1) <= 12.0
    np.testing.assert_array_equal(
        session.working, editable & in_region & (plane.distance(xyz) <= 0.5)
    )

    chosen = session.working.copy()
    session.assign(6)
    np.testing.assert_array_equal(session.labels, np.where(chosen, 6, labels))
    session.move_layer(6, 7)
    moved = np.where(chosen | (labels == 6), 7, labels)
    np.testing.assert_array_equal(session.labels, moved)
    with pytest.raises(OperationError, match="locked"):
        session.move_layer(3, 1)
    for _ in range(5):
        session.undo()
    np.testing.assert_array_equal(session.labels, labels)
    np.testing.assert_array_equal(session.working, expected)
    for _ in range(5):
        session.redo()
    np.testing.assert_array_equal(session.labels, moved)


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 300).flatmap(
        lambda n: st.tuples(
            st.lists(st.integers(0, 8), min_size=n, max_size=n),
            st.lists(st.integers(0, 8), min_size=n, max_size=n),
            st.lists(st.booleans(), min_size=n, max_size=n),
            st.lists(st.booleans(), min_size=n, max_size=n),
        )
    )
)
def test_a_delta_round_trips_exactly(arrays) -> None:
    before, after, working_before, working_after = (np.array(a) for a in arrays)
    before, after = before.astype(np.uint8), after.astype(np.uint8)
    delta = Delta.between(before, after, working_before, working_after)
    again = Delta.from_bytes(delta.to_bytes(), n_points=before.size)
    labels, working = before.copy(), working_before.copy()
    again.apply(labels, working)
    np.testing.assert_array_equal(labels, after)
    np.testing.assert_array_equal(working, working_after)
    again.revert(labels, working)
    np.testing.assert_array_equal(labels, before)
    np.testing.assert_array_equal(working, working_before)


def test_deltas_of_the_first_journal_format_are_read() -> None:
    buffer = io.BytesIO()
    changed = np.array([1, 4, 5])
    np.savez_compressed(
        buffer,
        changed=np.diff(changed, prepend=0),
        old=np.array([0, 0, 2], np.uint8),
        new=np.array([3, 3, 1], np.uint8),
        flip=np.diff(np.array([0, 5]), prepend=0),
    )
    delta = Delta.from_bytes(buffer.getvalue(), n_points=8)
    labels = np.array([0, 0, 0, 0, 0, 2, 0, 0], np.uint8)
    working = np.zeros(8, bool)
    delta.apply(labels, working)
    assert labels.tolist() == [0, 3, 0, 0, 3, 1, 0, 0]
    assert working.tolist() == [True, False, False, False, False, True, False, False]


def test_a_fit_passes_through_the_picks_and_stays_in_its_region(session, simulated_scan):
    xyz = _local(session)
    ground = simulated_scan.truth == 2
    centre = xyz[ground][np.argmin(np.linalg.norm(xyz[ground, :2], axis=1))]
    near = np.flatnonzero(ground & (np.linalg.norm(xyz - centre, axis=1) < 4))
    seeds = xyz[near[:: max(1, near.size // 4)][:4]]
    half = np.array([6.0, 6.0, 3.0])
    region = Region.box(centre - half, centre + half)
    preview = session.fit_preview("plane", seeds, tolerance_m=0.15, region=region)
    assert session.summary()["can_undo"] is False  # a preview changes nothing
    model = geometry.PlaneModel(np.array(preview.model["point"]), np.array(preview.model["normal"]))
    assert (model.distance(seeds) <= 0.15).all()
    assert preview.sample.shape[0] == min(preview.n_inliers, 30_000) > 100
    assert (np.abs(preview.sample - centre) <= (6.01, 6.01, 3.01)).all()
    result = session.fit("plane", seeds, tolerance_m=0.15, region=region, model=preview.model)
    assert result.n_inliers == preview.n_inliers == session.working.sum()
    chosen = xyz[session.working]
    assert (np.abs(chosen - centre) <= (6, 6, 3)).all()  # nothing beyond the region
    with pytest.raises(OperationError, match="within tolerance of every pick"):
        far = {**preview.model, "point": (np.array(preview.model["point"]) + 5).tolist()}
        session.fit("plane", seeds, tolerance_m=0.15, model=far)


def test_an_operation_reports_progress_and_can_be_cancelled(session, monkeypatch) -> None:
    monkeypatch.setattr("semantic3d.labelling.blocks.BLOCK_POINTS", 4096)
    reached = threading.Event()
    release = threading.Event()
    update = session.progress.update

    def slow(done: int) -> None:
        update(done)
        if done > 0:
            reached.set()
            release.wait(10)

    monkeypatch.setattr(session.progress, "update", slow)
    outcome: list[object] = []
    worker = threading.Thread(
        target=lambda: outcome.append(_catch(lambda: session.split(TOP_VIEW, TRIANGLE)))
    )
    before = session.working.copy()
    entries = len(session.journal.operations())
    worker.start()
    assert reached.wait(10)
    snapshot = session.progress.snapshot()
    assert snapshot["running"] and snapshot["operation"] == "split" and snapshot["cancellable"]
    assert 0 < snapshot["done"] < snapshot["total"] <= session.n_points
    assert session.cancel()
    release.set()
    worker.join(10)
    assert isinstance(outcome[0], OperationCancelledError)
    np.testing.assert_array_equal(session.working, before)
    assert len(session.journal.operations()) == entries
    assert not session.progress.snapshot()["running"] and not session.cancel()
    assert session.split(TOP_VIEW, TRIANGLE).n_working < session.n_points  # runs again


def _catch(call):  # type: ignore[no-untyped-def]
    try:
        return call()
    except Exception as exc:
        return exc


def test_counts_and_confusion_of_the_working_set_and_the_view(session, simulated_scan) -> None:
    truth = simulated_scan.truth
    session.labels[:] = truth
    session.split(TOP_VIEW, TRIANGLE)
    stats = selection_stats(session, scope="working")
    working = session.working
    prediction = session.prediction
    assert stats["counts"] == np.bincount(truth[working], minlength=9).tolist()
    expected = np.zeros((8, 8), int)
    labelled = working & (truth > 0)
    np.add.at(expected, (truth[labelled] - 1, prediction[labelled] - 1), 1)
    assert stats["confusion"] == expected.tolist()
    assert 0.8 < stats["overall_accuracy"] < 0.9  # one point in seven is wrong
    view = selection_stats(session, scope="view", view_projection=TOP_VIEW.reshape(-1))
    ndc, _ = geometry.project_to_ndc(_local(session), TOP_VIEW)
    depth = _local(session) @ TOP_VIEW[2, :3] + TOP_VIEW[2, 3]
    in_view = (np.abs(ndc) <= 1).all(axis=1) & (np.abs(depth) <= 1)
    assert view["counts"] == np.bincount(truth[in_view], minlength=9).tolist()


def _perspective(height_m: float = 80.0, focal: float = 1.5) -> np.ndarray:
    """A camera looking down from ``height_m`` (row-major view-projection, near 1, far 200)."""
    near, far = 1.0, 200.0
    a, b = -(far + near) / (far - near), -2 * far * near / (far - near)
    return np.array(
        [[focal, 0, 0, 0], [0, focal, 0, 0], [0, 0, a, b - a * height_m], [0, 0, -1, height_m]]
    )


def test_passes_on_threads_equal_the_pass_in_order(session, simulated_scan, monkeypatch) -> None:
    """Splits, masks, fits and counts over blocks on threads set the same bits as in order."""
    monkeypatch.setattr("semantic3d.labelling.blocks.BLOCK_POINTS", 4096)  # 10 blocks
    monkeypatch.setattr("semantic3d.labelling.node_split.TASK_POINTS", 4096)  # polygon splits
    truth = simulated_scan.truth
    session.labels[:] = truth
    session.set_layer(3, locked=True)
    xyz = _local(session)
    perspective = _perspective()
    mask = np.packbits(np.random.default_rng(2).random(64 * 48) < 0.5, bitorder="little")
    plane = {"kind": "plane", "point": [0.0, 0.0, float(np.median(xyz[:, 2]))]}
    plane["normal"] = [0.0, 0.0, 1.0]
    outcomes = []
    for threads in (1, 3):
        monkeypatch.setattr("semantic3d.labelling.blocks.block_threads", lambda t=threads: t)
        sets = []
        for operation in (
            lambda: session.split(perspective, TRIANGLE),
            lambda: session.split(TOP_VIEW, TRIANGLE, keep="outside"),
            lambda: session.split_mask(perspective, mask, width=64, height=48),
            lambda: session.fit("plane", [plane["point"]], tolerance_m=1.0, model=plane),
        ):
            session.reset()
            operation()
            sets.append(session.working.copy())
        view = selection_stats(session, scope="view", view_projection=perspective.reshape(-1))
        outcomes.append((sets, view["counts"]))
    for in_order, on_threads in zip(outcomes[0][0], outcomes[1][0], strict=True):
        assert 0 < in_order.sum() < 0.9 * in_order.size
        np.testing.assert_array_equal(in_order, on_threads)
    assert outcomes[0][1] == outcomes[1][1]
    # The perspective split (a division by w per point) equals the numpy reference.
    ndc, in_front = geometry.project_to_ndc(xyz, perspective)
    inside = geometry.points_in_polygon(ndc, TRIANGLE) & in_front
    editable = ~session.locked[truth]
    assert 0 < inside.sum() < inside.size
    np.testing.assert_array_equal(outcomes[0][0][0], editable & inside)


@pytest.fixture(scope="module")
def million_point_cache(tmp_path_factory):
    """A synthetic scan of 10**6 points (a noisy box), enough to tell bytes per point apart."""
    from semantic3d.core.pointcloud import PointCloud
    from semantic3d.io.cache import write_cache

    rng = np.random.default_rng(1)
    n = 1_000_000
    cloud = PointCloud(
        rng.uniform(-20, 20, (n, 3)),
        rng.integers(-2000, 2000, n).astype(np.int32),
        rng.integers(0, 255, (n, 3)).astype(np.uint8),
    )
    path = tmp_path_factory.mktemp("million") / "box.cache"
    write_cache(path, [cloud])
    return path


def test_operations_hold_about_one_byte_per_point(million_point_cache, tmp_path, monkeypatch):
    """Peak allocations of whole-scan operations: masks and old labels, never indices.

    At 10**6 points a list of int64 indices would take 8 MB, a copy of the labels 1 MB;
    the budget is two bit masks (250 kB), one byte per relabelled point (1 MB) and the
    compressor's fixed buffers, plus one block of coordinates per thread of a pass.
    """
    from semantic3d.labelling.blocks import block_threads

    block = 1 << 16
    monkeypatch.setattr("semantic3d.labelling.blocks.BLOCK_POINTS", block)
    session = open_label_session(million_point_cache, labels_path=tmp_path / "m.labels")
    n = session.n_points
    budget = 1.3 * n + 2_000_000 + (block_threads() - 1) * block * 24
    operations = (
        lambda: session.assign(4, confirm_whole_scan=True),
        session.undo,
        session.redo,
        lambda: session.split(TOP_VIEW, TRIANGLE),
        lambda: session.reset(),
        lambda: session.move_layer(4, 5),
        session.summary,
    )
    try:
        for operation in operations:  # compiled kernels loaded before measuring
            operation()
        peaks = []
        for operation in operations:
            tracemalloc.start()
            operation()
            peaks.append(tracemalloc.get_traced_memory()[1])
            tracemalloc.stop()
    finally:
        session.close()
    assert max(peaks) < budget, (peaks, budget)
