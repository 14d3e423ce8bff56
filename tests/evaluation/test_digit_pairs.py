"""The ``d\\n`` pair counter: a whole-window prefix counted, and the evaluation it speeds up
gives the same results and the same problems as the general parsers alone."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import SubmissionError
from semantic3d.core.threads import thread_limit
from semantic3d.evaluation import _digit_pair_kernel as kernel
from semantic3d.evaluation import custom_challenge, evaluate_submission
from semantic3d.evaluation import evaluate as evaluation
from tests.evaluation.conftest import write_zip

WINDOW = kernel.WINDOW


def _text(values: np.ndarray) -> bytearray:
    """``d\\n`` lines of single-digit ``values``."""
    out = bytearray(2 * values.shape[0])
    out[0::2] = (values.astype(np.uint8) + 48).tobytes()
    out[1::2] = b"\n" * values.shape[0]
    return out


@settings(max_examples=40, deadline=None)
@given(
    n_windows=st.integers(1, 6),
    extra=st.integers(0, WINDOW - 1),
    spoil=st.one_of(
        st.none(),
        st.tuples(
            st.sampled_from(["truth", "pred"]),
            st.integers(0, 6 * WINDOW - 1),
            st.sampled_from([b"x", b"\r", b" ", b"9", b"0"]),
            st.booleans(),  # the digit (True) or the line end
            st.sampled_from([1, 5, 32, 40, 300]),  # lines spoilt alike from that line on
        ),
    ),
    run_length=st.sampled_from([1, 3, 6, 8, 32, 33, 64, 1000, 10_000]),
    offsets=st.tuples(st.integers(0, 3), st.integers(0, 3)),
    n_threads=st.integers(1, 5),
    seed=st.integers(0, 2**16),
)
def test_the_counter_counts_the_windows_before_the_first_bad_line(
    n_windows: int,
    extra: int,
    spoil: tuple[str, int, bytes, bool, int] | None,
    run_length: int,
    offsets: tuple[int, int],
    n_threads: int,
    seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    n = n_windows * WINDOW + extra
    # labels in runs, as a scan's are (its blocks of one repeated pair counted at once),
    # with the prediction's runs shifted against the truth's
    runs = -(-n // run_length) + 1
    truth = np.repeat(rng.integers(0, 9, runs), run_length)[:n]
    shift = int(rng.integers(0, run_length))
    pred = np.repeat(rng.integers(1, 9, runs), run_length)[shift : shift + n]
    texts = {"truth": _text(truth), "pred": _text(pred)}
    first_bad = n
    if spoil is not None:
        which, line, byte, digit, n_spoilt = spoil
        line %= n
        for spoilt in range(line, min(n, line + n_spoilt)):
            at = 2 * spoilt + (0 if digit else 1)
            texts[which][at : at + 1] = byte
        # any byte in place of the line end is bad; truth accepts 0..8 and pred 1..8 here:
        # "9" is out of range for both, "0" for pred
        if not digit or byte in b"x\r 9" or (byte == b"0" and which == "pred"):
            first_bad = line
    buffers = {
        which: np.frombuffer(bytes(offsets[i]) + bytes(text), np.uint8)
        for i, (which, text) in enumerate(texts.items())
    }
    table = np.zeros((9, 9), np.int64)
    counted = kernel.count_digit_pairs(
        buffers["truth"], offsets[0], buffers["pred"], offsets[1], n, 0, 8, 1, 8, table, n_threads
    )
    expected = min(n_windows, first_bad // WINDOW) * WINDOW
    assert counted == expected
    reference = np.zeros((9, 9), np.int64)
    digits = {
        which: np.frombuffer(bytes(text), np.uint8)[0::2] - 48 for which, text in texts.items()
    }
    np.add.at(reference, (digits["truth"][:counted], digits["pred"][:counted]), 1)
    np.testing.assert_array_equal(table, reference)


@settings(max_examples=30, deadline=None)
@given(
    n_blocks=st.integers(0, 5),
    extra=st.integers(0, 2 * WINDOW),
    first=st.integers(0, 3 * WINDOW),
    spoil=st.one_of(
        st.none(),
        st.tuples(
            st.sampled_from(["truth", "pred"]),
            st.floats(0, 1, exclude_max=True),  # where, as a share of the counted lines
            st.sampled_from([b"x", b"\r", b"9", b"0"]),
            st.booleans(),  # the digit (True) or the line end
        ),
    ),
    n_threads=st.integers(1, 5),
    seed=st.integers(0, 2**16),
)
def test_the_file_counter_counts_every_line_or_nothing(
    n_blocks: int,
    extra: int,
    first: int,
    spoil: tuple[str, float, bytes, bool] | None,
    n_threads: int,
    seed: int,
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    # whole blocks of windows for the threads' runs, a tail of windows and single lines,
    # counted from line ``first`` on
    rng = np.random.default_rng(seed)
    n = n_blocks * kernel.BLOCK_WINDOWS * WINDOW + extra
    truth = np.repeat(rng.integers(0, 9, n // 50 + first + 1), 50)[: first + n]
    pred = np.where(
        rng.random(first + n) < 0.7, np.maximum(truth, 1), rng.integers(1, 9, first + n)
    )
    texts = {"truth": _text(truth), "pred": _text(pred)}
    good = True
    if spoil is not None and n:
        which, share, byte, digit = spoil
        at = 2 * (first + int(share * n)) + (0 if digit else 1)
        texts[which][at : at + 1] = byte
        # truth accepts 0..8 and pred 1..8 here: "9" is out of range for both, "0" for pred
        good = digit and byte == b"0" and which == "truth"
    folder = tmp_path_factory.mktemp("files")
    for which, text in texts.items():
        (folder / which).write_bytes(text)
    table = np.ones((9, 9), np.int64)
    with (folder / "truth").open("rb") as t, (folder / "pred").open("rb") as p:
        counted = kernel.count_file_pairs(
            t.fileno(), p.fileno(), first, n, 0, 8, 1, 8, table, n_threads
        )
    assert counted == good
    reference = np.ones((9, 9), np.int64)
    if good:
        digits = {w: np.frombuffer(bytes(text), np.uint8)[0::2] - 48 for w, text in texts.items()}
        np.add.at(reference, (digits["truth"][first:], digits["pred"][first:]), 1)
    np.testing.assert_array_equal(table, reference)  # untouched when not every line counts


def test_the_file_counter_counts_nothing_past_the_end_of_a_file(tmp_path: Path) -> None:
    text = _text(np.full(3 * WINDOW + 5, 4))
    (tmp_path / "whole").write_bytes(text)
    (tmp_path / "short").write_bytes(text[:-2])
    table = np.zeros((9, 9), np.int64)
    with (tmp_path / "whole").open("rb") as whole, (tmp_path / "short").open("rb") as short:
        for truth, pred, n in ((whole, short, 3 * WINDOW + 5), (whole, whole, 4 * WINDOW)):
            assert not kernel.count_file_pairs(
                truth.fileno(), pred.fileno(), 0, n, 0, 8, 0, 8, table, 2
            )
        assert kernel.count_file_pairs(
            whole.fileno(), short.fileno(), 0, 3 * WINDOW + 4, 0, 8, 0, 8, table, 2
        )
    assert table[4, 4] == table.sum() == 3 * WINDOW + 4


def test_the_counter_adds_to_its_table_and_ignores_a_short_tail() -> None:
    values = np.full(WINDOW - 1, 3)
    table = np.ones((9, 9), np.int64)
    text = np.frombuffer(bytes(_text(values)), np.uint8)
    assert kernel.count_digit_pairs(text, 0, text, 0, WINDOW - 1, 0, 8, 0, 8, table, 2) == 0
    np.testing.assert_array_equal(table, 1)
    values = np.full(2 * WINDOW, 3)
    text = np.frombuffer(bytes(_text(values)), np.uint8)
    assert (
        kernel.count_digit_pairs(text, 0, text, 0, 2 * WINDOW, 0, 8, 0, 8, table, 2) == 2 * WINDOW
    )
    assert table[3, 3] == 1 + 2 * WINDOW
    assert table.sum() == 81 + 2 * WINDOW


# --- the evaluation: long files go through the counter, with the same outcome ---------------

N_LINES = 700_000  # more than the counter's first read (1 MiB a file), so it runs


def _scan_texts(seed: int, runs: bool = False) -> tuple[bytearray, bytearray]:
    rng = np.random.default_rng(seed)
    if runs:  # as a scan's: runs of one class, the prediction wrong in runs too
        truth = np.repeat(rng.integers(0, 9, N_LINES), rng.geometric(1 / 100, N_LINES))
        wrong = np.repeat(rng.random(N_LINES) < 0.2, rng.geometric(1 / 50, N_LINES))
        truth, wrong = truth[:N_LINES], wrong[:N_LINES]
        return _text(truth), _text(np.where(wrong, truth % 8 + 1, np.maximum(truth, 1)))
    truth = rng.integers(0, 9, N_LINES)
    pred = np.where(rng.random(N_LINES) < 0.8, np.maximum(truth, 1), rng.integers(1, 9, N_LINES))
    return _text(truth), _text(pred)


def _splice(text: bytearray, line: int, replacement: bytes) -> bytearray:
    """``text`` with its line ``line`` (1-based) replaced by ``replacement`` (its line end too)."""
    at = 2 * (line - 1)
    return text[:at] + bytearray(replacement) + text[at + 2 :]


CASES = {
    "clean": {},
    "crlf line": {"pred": [(300_001, b"4\r\n")]},
    "padded values": {"pred": [(5, b" 4\n"), (600_000, b"4\t\n")], "truth": [(70_000, b"2 \n")]},
    "two digits": {"pred": [(123_457, b"12\n")]},
    "out of range": {"pred": [(2, b"9\n"), (650_000, b"0\n")]},
    "not a number": {"pred": [(400_000, b"x\n"), (400_001, b"\n")]},
    "bad truth": {"truth": [(555_555, b"9\n")]},
    "missing line": {"pred": [(99_999, b"")]},
    "extra line": {"pred": [(N_LINES, b"1\n2\n")]},
    "no final line end": {"pred": [(N_LINES, b"1")]},
    "crlf file": {"pred": "crlf"},
}


def _outcome(submission: Path, truth_dir: Path, **kwargs: int) -> tuple[object, ...]:
    try:
        result = evaluate_submission(submission, challenge=custom_challenge(truth_dir), **kwargs)
    except SubmissionError as exc:
        return ("problems", exc.problems)
    except Exception as exc:
        return ("error", type(exc).__name__, str(exc))
    return ("scores", result.to_dict())


def _recording(monkeypatch: pytest.MonkeyPatch, name: str) -> list[object]:
    """What the kernel ``name`` returns, call by call, from now on."""
    returned: list[object] = []
    real = getattr(kernel, name)

    def recording(*args: object) -> object:
        returned.append(real(*args))
        return returned[-1]

    monkeypatch.setattr(kernel, name, recording)
    return returned


@pytest.mark.parametrize("case", list(CASES))
def test_long_files_give_what_the_general_parsers_alone_give(
    case: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    truth_dir, sub_dir = tmp_path / "truth", tmp_path / "sub"
    truth_dir.mkdir()
    sub_dir.mkdir()
    members = {}
    for i, name in enumerate(("a.labels", "b.labels")):
        truth, pred = _scan_texts(i, runs=i == 0)
        texts = {"truth": truth, "pred": pred}
        edits = CASES[case] if i == 0 else {}
        for which, changes in edits.items():
            if changes == "crlf":
                texts[which] = bytearray(bytes(texts[which]).replace(b"\n", b"\r\n"))
                continue
            for line, replacement in sorted(changes, reverse=True):
                texts[which] = _splice(texts[which], line, replacement)
        (truth_dir / name).write_bytes(texts["truth"])
        (sub_dir / name).write_bytes(texts["pred"])
        members[name] = bytes(texts["pred"])
    archive = write_zip(tmp_path / "sub.zip", members, compression=zipfile.ZIP_DEFLATED)

    calls = _recording(monkeypatch, "count_digit_pairs")
    files = _recording(monkeypatch, "count_file_pairs")
    with monkeypatch.context() as only_streams:
        only_streams.setattr(evaluation, "_count_digit_files", lambda *args: None)
        general = _outcome(sub_dir, truth_dir, chunk_size=evaluation._RETRY_PAIRS)  # no counter
        assert calls == [] and files == []
        assert _outcome(sub_dir, truth_dir) == general  # the streams' counter alone
    calls.clear()
    for submission in (sub_dir, archive):
        assert _outcome(submission, truth_dir) == general
    # scan b's files (and a's when clean) were counted whole by the file counter; it gave up
    # on scan a's files of one length with a bad line (the streams took them), and was not
    # tried on files of different lengths (scans run side by side: sorted)
    tried_a = {"clean": [True], "out of range": [False], "bad truth": [False]}.get(case, [])
    expected = [sorted([*tried_a, True])]
    if case == "bad truth":  # its error may end the evaluation before scan b
        expected.append([False])
    assert sorted(files) in expected
    # the streams' counter did the bulk of the work the file counter left (the archive's
    # scans at least), but where a whole file has another shape
    assert sum(calls) >= (N_LINES if case == "crlf file" else 2 * N_LINES) - 4 * 2 * WINDOW
    if case == "crlf file":  # a few windows tried, then the general parsers alone
        assert len([c for c in calls if c == 0]) <= 2 * 12
    if case in ("clean", "crlf line", "padded values", "crlf file", "no final line end"):
        assert general[0] == "scores"
    elif case == "bad truth":
        assert general[0] == "error"
    else:
        assert general[0] == "problems"


def test_the_counter_gives_the_same_numbers_on_any_number_of_threads(tmp_path: Path) -> None:
    truth_dir, sub_dir = tmp_path / "truth", tmp_path / "sub"
    truth_dir.mkdir()
    sub_dir.mkdir()
    truth, pred = _scan_texts(7)
    (truth_dir / "a.labels").write_bytes(truth)
    (sub_dir / "a.labels").write_bytes(pred)
    outcomes = []
    for n_threads in (1, 2, 3):
        with thread_limit(n_threads):
            outcomes.append(_outcome(sub_dir, truth_dir))
            with zipfile.ZipFile(tmp_path / f"{n_threads}.zip", "w") as archive:
                archive.write(sub_dir / "a.labels", "a.labels")  # streamed, not a file
            outcomes.append(_outcome(tmp_path / f"{n_threads}.zip", truth_dir))
    assert all(outcome == outcomes[0] for outcome in outcomes)
    assert outcomes[0][0] == "scores"


def test_the_retry_step_passes_a_whole_counter_window() -> None:
    assert evaluation._RETRY_PAIRS >= WINDOW


def test_a_bad_line_anywhere_in_a_window_spoils_it_whatever_the_runs_around_it() -> None:
    # the counter checks a pair only where it differs from the one before (or, in a span
    # of many changes, every pair): a bad line at any place, alone or starting a run of
    # bad lines to the window's end, behind busy spans and long runs alike
    rng = np.random.default_rng(5)
    truth = np.repeat(rng.integers(1, 9, WINDOW), rng.integers(1, 200, WINDOW))[:WINDOW]
    truth[:700] = np.arange(700) % 7 + 1  # a busy start: a change every line
    truth[2000:2300] = rng.integers(1, 9, 300)
    pred = np.maximum(truth, 1)
    clean = np.frombuffer(bytes(_text(truth)), np.uint8)
    reference = np.zeros((9, 9), np.int64)
    np.add.at(reference, (truth, pred), 1)
    table = np.zeros((9, 9), np.int64)
    pred_text = np.frombuffer(bytes(_text(pred)), np.uint8)
    assert kernel.count_digit_pairs(clean, 0, pred_text, 0, WINDOW, 0, 8, 1, 8, table, 1) == WINDOW
    np.testing.assert_array_equal(table, reference)
    for line in range(WINDOW):
        for to_the_end in (False, True):
            spoilt = clean.copy()
            spoilt[2 * line : 2 * WINDOW if to_the_end else 2 * line + 1 : 2] = ord("9")
            table = np.zeros((9, 9), np.int64)
            got = kernel.count_digit_pairs(spoilt, 0, pred_text, 0, WINDOW, 0, 8, 1, 8, table, 1)
            assert got == 0, (line, to_the_end)
            assert not table.any()  # the window taken back
