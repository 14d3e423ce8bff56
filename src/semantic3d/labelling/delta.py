"""What one labelling operation changed, as packed bit masks: exact both ways, small.

A :class:`Delta` holds a bit per point for "label changed" and one for "entered or left
the working set", plus the old label of each changed point and their new label (one
value when they all took the same, as *assign* and *move layer* give). At 10**8 points a
whole-scan assignment is two 12.5 MB masks and 100 MB of old labels, instead of the
800 MB of int64 indices a list of positions would take, and it compresses to a few MB.

Serialised form (journal payloads, version 2)::

    b"S3DD" | uint32 header length | JSON header | zlib(changed) | zlib(old) | zlib(new) | zlib(flip)

zlib at level 1: masks of a local operation are mostly zero bytes and compress a
thousandfold at that level, faster than the journal's fsync. Payloads of the first journal
format (``np.savez`` of int64 indices) are still read.
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.labelling import _op_kernels as kernels

__all__ = ["Delta", "bits_from_mask", "empty_bits"]

_MAGIC = b"S3DD"
_LEVEL = 1


def empty_bits(n_points: int) -> NDArray[np.uint8]:
    """A mask of ``n_points`` bits, all clear."""
    return np.zeros((n_points + 7) // 8, np.uint8)


def bits_from_mask(mask: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """The packed form of a boolean mask."""
    return np.packbits(mask, bitorder="little")


def _indices_to_bits(indices: NDArray[np.int64], n_points: int) -> NDArray[np.uint8]:
    mask = np.zeros(n_points, bool)
    mask[indices] = True
    return bits_from_mask(mask)


@dataclass(frozen=True, slots=True)
class Delta:
    """One operation's change.

    Attributes:
        n_points: points of the scan.
        changed: bit mask of the points whose label changed.
        old_labels: their labels before, in index order.
        new_labels: their labels after, in index order, or ``None`` with ``new_value``.
        new_value: the one label every changed point took (``-1``: see ``new_labels``).
        working_flip: bit mask of the points that entered or left the working set.
    """

    n_points: int
    changed: NDArray[np.uint8]
    old_labels: NDArray[np.uint8]
    new_labels: NDArray[np.uint8] | None
    new_value: int
    working_flip: NDArray[np.uint8]

    @classmethod
    def working_only(cls, n_points: int, flip: NDArray[np.uint8]) -> Delta:
        """A change of the working set alone."""
        return cls(n_points, empty_bits(n_points), np.empty(0, np.uint8), None, 0, flip)

    @classmethod
    def between(
        cls,
        labels_before: NDArray[np.uint8],
        labels_after: NDArray[np.uint8],
        working_before: NDArray[np.bool_],
        working_after: NDArray[np.bool_],
    ) -> Delta:
        """The delta from one state to another (a reference; operations build theirs directly)."""
        changed = labels_before != labels_after
        new = labels_after[changed]
        single = int(new[0]) if new.size and (new == new[0]).all() else -1
        return cls(
            labels_before.size,
            bits_from_mask(changed),
            labels_before[changed],
            None if single >= 0 or new.size == 0 else new,
            max(single, 0) if new.size == 0 else single,
            bits_from_mask(working_before != working_after),
        )

    @property
    def n_changed(self) -> int:
        return int(self.old_labels.size)

    @property
    def n_flipped(self) -> int:
        return int(kernels.count_bits(self.working_flip))

    @property
    def is_empty(self) -> bool:
        return self.n_changed == 0 and not self.working_flip.any()

    def _values(self, forward: bool) -> tuple[NDArray[np.uint8], int]:
        if not forward:
            return self.old_labels, -1
        if self.new_labels is None:
            return self.old_labels, self.new_value
        return self.new_labels, -1

    def apply(self, labels: NDArray[np.uint8], working: NDArray[np.bool_]) -> None:
        """Redo the change in place."""
        values, single = self._values(True)
        kernels.apply_delta(labels, working, self.changed, values, single, self.working_flip, True)

    def revert(self, labels: NDArray[np.uint8], working: NDArray[np.bool_]) -> None:
        """Undo the change in place."""
        values, single = self._values(False)
        kernels.apply_delta(labels, working, self.changed, values, single, self.working_flip, False)

    def to_bytes(self) -> bytes:
        arrays = (self.changed, self.old_labels, self.new_labels, self.working_flip)
        parts = [
            zlib.compress(b"" if a is None else memoryview(np.ascontiguousarray(a)), _LEVEL)  # type: ignore[arg-type]
            for a in arrays
        ]
        header = json.dumps(
            {
                "version": 2,
                "n_points": self.n_points,
                "n_changed": self.n_changed,
                "new_value": self.new_value,
                "sizes": [len(p) for p in parts],
            }
        ).encode()
        return b"".join([_MAGIC, struct.pack("<I", len(header)), header, *parts])

    @classmethod
    def from_bytes(cls, data: bytes, *, n_points: int) -> Delta:
        if not data.startswith(_MAGIC):
            return cls._from_first_format(data, n_points)
        (length,) = struct.unpack_from("<I", data, 4)
        header = json.loads(data[8 : 8 + length])
        at = 8 + length
        arrays = []
        for size in header["sizes"]:
            arrays.append(np.frombuffer(zlib.decompress(data[at : at + size]), np.uint8))
            at += size
        changed, old, new, flip = arrays
        return cls(
            int(header["n_points"]),
            changed,
            old,
            new if new.size else None,
            int(header["new_value"]),
            flip,
        )

    @classmethod
    def _from_first_format(cls, data: bytes, n_points: int) -> Delta:
        with np.load(io.BytesIO(data), allow_pickle=False) as arrays:
            changed = np.cumsum(arrays["changed"]).astype(np.int64)
            flip = np.cumsum(arrays["flip"]).astype(np.int64)
            old, new = arrays["old"], arrays["new"]
        return cls(
            n_points,
            _indices_to_bits(changed, n_points),
            np.asarray(old, np.uint8),
            np.asarray(new, np.uint8) if new.size else None,
            0 if new.size == 0 else -1,
            _indices_to_bits(flip, n_points),
        )
