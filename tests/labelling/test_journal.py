"""The journal: undo/redo, a crash in the middle of an operation, resuming, stale journals."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from semantic3d.core.errors import OutputExistsError
from semantic3d.io import read_labels
from semantic3d.labelling.errors import JournalError, OperationError
from semantic3d.labelling.journal import Journal
from semantic3d.labelling.opening import journal_path_for, open_label_session

from .conftest import NODE_CAPACITY

TOP_VIEW = np.diag([0.02, 0.02, -0.001, 1.0])  # x, y in [-50, 50] m fill the screen
SQUARE = [(-0.2, -0.2), (0.2, -0.2), (0.2, 0.2), (-0.2, 0.2)]


def _open(scan, labels: Path):
    return open_label_session(scan.cache.path, labels_path=labels, node_capacity=NODE_CAPACITY)


def test_undo_redo_and_resume(simulated_scan, tmp_path: Path) -> None:
    labels_path = tmp_path / "mine.labels"
    session = _open(simulated_scan, labels_path)
    n = session.n_points
    split = session.split(TOP_VIEW, SQUARE, keep="inside")
    assert 0 < split.n_working < n
    inside = session.working.copy()
    session.assign(2)
    session.reset(scope="unlabelled")
    assert session.working.sum() == n - inside.sum()
    session.split(TOP_VIEW, SQUARE, keep="outside")  # nothing unlabelled inside anyway
    session.assign(5)
    np.testing.assert_array_equal(session.labels, np.where(inside, 2, 5))
    session.undo()
    np.testing.assert_array_equal(session.labels, np.where(inside, 2, 0))
    session.undo()
    session.undo()
    session.redo()
    expected_labels, expected_working = session.labels.copy(), session.working.copy()
    assert len(session.undo_stack) == 3 and len(session.redo_stack) == 2
    session.close()

    resumed = _open(simulated_scan, labels_path)  # nothing saved: the journal alone resumes
    np.testing.assert_array_equal(resumed.labels, expected_labels)
    np.testing.assert_array_equal(resumed.working, expected_working)
    assert len(resumed.undo_stack) == 3 and len(resumed.redo_stack) == 2
    resumed.redo()
    resumed.assign(3)  # a new operation clears the redo stack
    with pytest.raises(OperationError, match="nothing to redo"):
        resumed.redo()
    saved = resumed.save()
    np.testing.assert_array_equal(read_labels(saved), resumed.labels)
    resumed.close()
    again = _open(simulated_scan, labels_path)  # the saved file and the journal agree
    np.testing.assert_array_equal(again.labels, read_labels(saved))
    assert len(again.undo_stack) == 5
    again.undo()  # undo reaches back before the save
    assert (again.labels == 3).sum() == 0
    again.close()


def test_a_crash_mid_operation_loses_only_that_operation(simulated_scan, tmp_path: Path) -> None:
    labels_path = tmp_path / "crash.labels"
    script = textwrap.dedent(
        f"""
        import os, signal
        import numpy as np
        from semantic3d.labelling.opening import open_label_session
        s = open_label_session({str(simulated_scan.cache.path)!r},
                               labels_path={str(labels_path)!r}, node_capacity={NODE_CAPACITY})
        s.split(np.diag([0.02, 0.02, -0.001, 1.0]), {SQUARE!r})
        s.assign(6)
        # The next operation is killed half way through its transaction.
        s.journal._connection.execute("BEGIN IMMEDIATE")
        s.journal._connection.execute(
            "INSERT INTO entries (kind, operation, payload, created_s) "
            "VALUES ('apply', '{{}}', x'00', 0)"
        )
        os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, check=False)
    assert done.returncode == -9, done.stderr.decode()
    assert not labels_path.exists()
    resumed = _open(simulated_scan, labels_path)
    assert len(resumed.undo_stack) == 2  # split and assign survived, the torn entry did not
    assert (resumed.labels == 6).sum() == resumed.working.sum() > 0
    assert all(entry["created_s"] > 0 for entry in resumed.journal.operations())
    resumed.close()


def test_a_labels_file_changed_elsewhere_starts_a_new_journal(simulated_scan, tmp_path) -> None:
    labels_path = tmp_path / "edited.labels"
    session = _open(simulated_scan, labels_path)
    session.split(TOP_VIEW, SQUARE)
    session.assign(1)
    session.save()
    session.close()
    labels_path.write_text("4\n" * simulated_scan.cache.n_points)  # edited by another tool
    with pytest.raises(OutputExistsError, match="not written by a labelling session"):
        _open(simulated_scan, labels_path)  # no longer ours: never written over untold
    assert labels_path.read_text() == "4\n" * simulated_scan.cache.n_points
    reopened = open_label_session(
        simulated_scan.cache.path,
        labels_path=labels_path,
        overwrite=True,
        node_capacity=NODE_CAPACITY,
    )
    assert (reopened.labels == 4).all() and reopened.undo_stack == []
    assert len(list(tmp_path.glob("edited.labels.journal.stale-????????"))) == 1
    reopened.close()


def test_a_touched_but_unchanged_file_keeps_its_journal(simulated_scan, tmp_path) -> None:
    labels_path = tmp_path / "touched.labels"
    session = _open(simulated_scan, labels_path)
    session.split(TOP_VIEW, SQUARE)
    session.assign(1)
    session.save()
    session.close()
    os.utime(labels_path, ns=(1, 1))  # copied back, touched: same bytes, new identity
    resumed = _open(simulated_scan, labels_path)
    assert len(resumed.undo_stack) == 2
    resumed.close()


_KILL_AFTER_RENAME = """
import os, signal
import numpy as np
from semantic3d.io import staging
from semantic3d.labelling.opening import open_label_session

rename = staging.StagedPath.commit
def commit_then_die(self):
    rename(self)          # the new file is in place...
    os.kill(os.getpid(), signal.SIGKILL)   # ...and the process dies before the journal hears of it
s = open_label_session({cache!r}, labels_path={labels!r}, node_capacity={capacity})
s.split(np.diag([0.02, 0.02, -0.001, 1.0]), {square!r})
s.assign(6)
{first_save}
s.reset(scope="unlabelled")
s.assign(3)
staging.StagedPath.commit = commit_then_die
s.save()
"""


@pytest.mark.parametrize("saved_before", [False, True])
def test_a_kill_between_the_rename_and_the_journal_keeps_the_history(
    simulated_scan, tmp_path: Path, saved_before: bool
) -> None:
    labels_path = tmp_path / "killed.labels"
    script = _KILL_AFTER_RENAME.format(
        cache=str(simulated_scan.cache.path),
        labels=str(labels_path),
        capacity=NODE_CAPACITY,
        square=SQUARE,
        first_save="s.save()" if saved_before else "",
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, check=False, env=env)
    assert done.returncode == -9, done.stderr.decode()
    on_disk = read_labels(labels_path)
    assert (on_disk == 3).any() and (on_disk == 6).any()  # the rename happened
    resumed = _open(simulated_scan, labels_path)
    np.testing.assert_array_equal(resumed.labels, on_disk)
    assert len(resumed.undo_stack) == 4  # split, assign, reset, assign: nothing thrown away
    assert not list(tmp_path.glob("*.stale-*"))
    resumed.undo()
    assert not (resumed.labels == 3).any()
    resumed.close()
    again = _open(simulated_scan, labels_path)  # the new identity was recorded on resume
    assert len(again.undo_stack) == 3 and len(again.redo_stack) == 1
    again.close()


def test_a_journal_of_another_scan_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "x.journal"
    Journal(path, scan_id="aaaa", n_points=10).close()
    with pytest.raises(JournalError, match="expected the journal of scan bbbb"):
        Journal(path, scan_id="bbbb", n_points=10)
    os.truncate(path, 0)
    path.write_bytes(b"not a database" * 100)
    with pytest.raises(JournalError, match="unreadable"):
        Journal(path, scan_id="aaaa", n_points=10)


def test_journal_lives_beside_the_labels() -> None:
    assert journal_path_for(Path("a/b.labels")) == Path("a/b.labels.journal")


def test_mask_kernels_equal_numpy_at_any_length() -> None:
    """Counting the bits of a mask and flipping the working set by it (8 points a byte,
    a partial last byte) equal numpy's unpacked masks."""
    from semantic3d.labelling import _op_kernels

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 8, 9, 63, 64, 65, 1001):
        chosen = rng.random(n) < 0.6
        chosen[: n // 3] = True  # whole bytes set, and mixed ones
        flip = np.packbits(chosen, bitorder="little")
        assert _op_kernels.count_bits(flip) == chosen.sum()
        working = rng.random(n) < 0.5
        labels = rng.integers(0, 9, n).astype(np.uint8)
        expected_working, expected_labels = working ^ chosen, labels.copy()
        _op_kernels.apply_delta(
            labels, working, np.zeros_like(flip), np.zeros(0, np.uint8), -1, flip, True
        )
        np.testing.assert_array_equal(working, expected_working, err_msg=str(n))
        np.testing.assert_array_equal(labels, expected_labels)
