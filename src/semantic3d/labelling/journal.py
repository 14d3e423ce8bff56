"""The labelling journal: every operation an entry in an append-only SQLite file.

Entries are never changed or removed. ``apply`` entries hold an operation (its name and
parameters, JSON) and its exact *delta*: which points changed label (old and new values)
and which points entered or left the working set. ``undo`` / ``redo`` entries name the
``apply`` entry they revert or reapply; ``checkpoint`` entries hold the whole state
(labels and working set, compressed), written when the journal starts and at each save.
Deltas are packed bit masks (:mod:`~semantic3d.labelling.delta`); payloads of the first
format (int64 indices in ``np.savez``) are still read.

State = the last checkpoint + every later entry's delta, replayed in order; the undo and
redo stacks are rebuilt from the entry kinds alone. Each entry is one SQLite transaction in
WAL mode with ``synchronous=FULL``, so a crash or a closed tab loses at most the operation
in flight, and the file is always consistent.
"""

from __future__ import annotations

import io
import json
import sqlite3
import struct
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.labelling.delta import Delta, bits_from_mask
from semantic3d.labelling.errors import JournalError

__all__ = ["Delta", "Journal", "JournalState"]  # Delta: re-exported from delta

JOURNAL_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL CHECK (kind IN ('apply', 'undo', 'redo', 'checkpoint')),
    target INTEGER REFERENCES entries(id),
    operation TEXT,
    payload BLOB,
    created_s REAL NOT NULL
);
"""


_CHECKPOINT_MAGIC = b"S3DC"


def _checkpoint_bytes(labels: NDArray[np.uint8], working: NDArray[np.bool_]) -> bytes:
    labels_part = zlib.compress(memoryview(np.ascontiguousarray(labels)), 1)  # type: ignore[arg-type]
    working_part = zlib.compress(bits_from_mask(working).tobytes(), 1)
    header = json.dumps(
        {"n_points": int(labels.size), "sizes": [len(labels_part), len(working_part)]}
    )
    encoded = header.encode()
    return b"".join(
        [_CHECKPOINT_MAGIC, struct.pack("<I", len(encoded)), encoded, labels_part, working_part]
    )


def _checkpoint_arrays(
    payload: bytes, n_points: int
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    if not payload.startswith(_CHECKPOINT_MAGIC):  # the first format: np.savez_compressed
        with np.load(io.BytesIO(payload), allow_pickle=False) as arrays:
            labels = np.array(arrays["labels"], np.uint8)
            working = np.unpackbits(arrays["working"], count=n_points).astype(bool)
        return labels, working
    (length,) = struct.unpack_from("<I", payload, 4)
    header = json.loads(payload[8 : 8 + length])
    at = 8 + length
    first, second = header["sizes"]
    labels = np.frombuffer(zlib.decompress(payload[at : at + first]), np.uint8).copy()
    bits = np.frombuffer(zlib.decompress(payload[at + first : at + first + second]), np.uint8)
    working = np.unpackbits(bits, count=n_points, bitorder="little").view(bool)
    return labels, working


@dataclass(slots=True)
class JournalState:
    """The state a journal replays to: labels, working set and the undo/redo stacks."""

    labels: NDArray[np.uint8]
    working: NDArray[np.bool_]
    undo_stack: list[int] = field(default_factory=list)
    redo_stack: list[int] = field(default_factory=list)
    n_entries: int = 0


class Journal:
    """An opened journal file (a context manager; closing it keeps every committed entry)."""

    def __init__(self, path: str | Path, *, scan_id: str, n_points: int) -> None:
        self.path = Path(path)
        self.n_points = n_points
        self._connection = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            self._connection.execute("PRAGMA journal_mode=WAL")
            self._connection.execute("PRAGMA synchronous=FULL")
            self._connection.executescript(_SCHEMA)
            meta = self.meta()
        except sqlite3.DatabaseError as exc:
            self._connection.close()
            raise JournalError(
                f"expected a labelling journal (SQLite), found an unreadable file: {exc}",
                path=str(self.path),
            ) from exc
        if not meta:
            self._set_meta({"version": JOURNAL_VERSION, "scan_id": scan_id, "n_points": n_points})
        elif meta.get("scan_id") != scan_id or meta.get("n_points") != n_points:
            self._connection.close()
            raise JournalError(
                f"expected the journal of scan {scan_id} ({n_points} points), found one of "
                f"scan {meta.get('scan_id')} ({meta.get('n_points')} points)",
                path=str(self.path),
            )

    @staticmethod
    def read_meta(path: str | Path) -> dict[str, Any] | None:
        """The meta values of the journal at ``path`` without changing it; ``None`` if unreadable."""
        try:
            connection = sqlite3.connect(f"{Path(path).resolve().as_uri()}?mode=ro", uri=True)
        except sqlite3.Error:
            return None
        try:
            rows = connection.execute("SELECT key, value FROM meta").fetchall()
            return {key: json.loads(value) for key, value in rows}
        except (sqlite3.Error, ValueError):
            return None
        finally:
            connection.close()

    # -- meta ---------------------------------------------------------------------------------

    def meta(self) -> dict[str, Any]:
        """Every meta value (JSON-decoded)."""
        rows = self._connection.execute("SELECT key, value FROM meta").fetchall()
        return {key: json.loads(value) for key, value in rows}

    def _set_meta(self, values: dict[str, Any]) -> None:
        with self._transaction():
            self._write_meta(values)

    def _write_meta(self, values: dict[str, Any]) -> None:
        self._connection.executemany(
            "INSERT INTO meta (key, value) VALUES (?, ?) "
            "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
            [(key, json.dumps(value)) for key, value in values.items()],
        )

    def set_meta(self, **values: Any) -> None:
        """Store settings (layer visibility and locks, the saved file's identity)."""
        self._set_meta(values)

    # -- entries ------------------------------------------------------------------------------

    def _transaction(self) -> _Transaction:
        return _Transaction(self._connection)

    def append_apply(self, operation: dict[str, Any], delta: Delta) -> int:
        """Record an operation and its delta (one transaction); return the entry id."""
        with self._transaction():
            cursor = self._connection.execute(
                "INSERT INTO entries (kind, operation, payload, created_s) VALUES ('apply', ?, ?, ?)",
                (json.dumps(operation), delta.to_bytes(), time.time()),
            )
        return int(cursor.lastrowid or 0)

    def append_step(self, kind: str, target: int) -> int:
        """Record an ``undo`` or ``redo`` of the apply entry ``target``."""
        if kind not in ("undo", "redo"):
            raise ValueError(f"kind: expected 'undo' or 'redo', found {kind!r}")
        with self._transaction():
            cursor = self._connection.execute(
                "INSERT INTO entries (kind, target, created_s) VALUES (?, ?, ?)",
                (kind, target, time.time()),
            )
        return int(cursor.lastrowid or 0)

    def append_checkpoint(
        self,
        labels: NDArray[np.uint8],
        working: NDArray[np.bool_],
        *,
        note: str,
        meta: dict[str, Any] | None = None,
    ) -> int:
        """Record the whole state (and optionally meta values) in one transaction."""
        payload = _checkpoint_bytes(labels, working)
        with self._transaction():
            cursor = self._connection.execute(
                "INSERT INTO entries (kind, operation, payload, created_s) "
                "VALUES ('checkpoint', ?, ?, ?)",
                (json.dumps({"note": note}), payload, time.time()),
            )
            if meta:
                self._write_meta(meta)
        return int(cursor.lastrowid or 0)

    def delta(self, entry_id: int) -> Delta:
        """The delta of the apply entry ``entry_id``."""
        row = self._connection.execute(
            "SELECT payload FROM entries WHERE id = ? AND kind = 'apply'", (entry_id,)
        ).fetchone()
        if row is None:
            raise JournalError(f"expected apply entry #{entry_id}, found none", path=str(self.path))
        return Delta.from_bytes(row[0], n_points=self.n_points)

    def operations(self) -> list[dict[str, Any]]:
        """Every entry, oldest first, without payloads (for the history panel)."""
        rows = self._connection.execute(
            "SELECT id, kind, target, operation, created_s FROM entries ORDER BY id"
        ).fetchall()
        return [
            {
                "id": row[0],
                "kind": row[1],
                "target": row[2],
                "operation": None if row[3] is None else json.loads(row[3]),
                "created_s": row[4],
            }
            for row in rows
        ]

    def replay(self) -> JournalState | None:
        """The state the entries lead to, or ``None`` when there is no checkpoint yet."""
        rows = self._connection.execute(
            "SELECT id, kind, target FROM entries ORDER BY id"
        ).fetchall()
        last_checkpoint = max((row[0] for row in rows if row[1] == "checkpoint"), default=None)
        if last_checkpoint is None:
            return None
        payload = self._connection.execute(
            "SELECT payload FROM entries WHERE id = ?", (last_checkpoint,)
        ).fetchone()[0]
        labels, working = _checkpoint_arrays(payload, self.n_points)
        state = JournalState(labels, working, n_entries=len(rows))
        for entry_id, kind, target in rows:
            after = entry_id > last_checkpoint
            if kind == "apply":
                state.undo_stack.append(entry_id)
                state.redo_stack.clear()
                if after:
                    self.delta(entry_id).apply(state.labels, state.working)
            elif kind == "undo":
                state.undo_stack.remove(target)
                state.redo_stack.append(target)
                if after:
                    self.delta(target).revert(state.labels, state.working)
            elif kind == "redo":
                state.redo_stack.remove(target)
                state.undo_stack.append(target)
                if after:
                    self.delta(target).apply(state.labels, state.working)
        return state

    def close(self) -> None:
        """Close the file (every committed entry stays)."""
        self._connection.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT``, rolled back on any exception."""

    def __init__(self, connection: sqlite3.Connection) -> None:
        self._connection = connection

    def __enter__(self) -> None:
        self._connection.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: type[BaseException] | None, *rest: object) -> None:
        if exc_type is None:
            self._connection.execute("COMMIT")
        else:
            self._connection.execute("ROLLBACK")
