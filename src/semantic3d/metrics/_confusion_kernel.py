"""The compiled counter of :class:`~semantic3d.metrics.confusion.ConfusionMatrix`.

A module of its own so that importing the metrics does not import numba: small updates
(a test file, a scan of a few thousand points) are counted with numpy, which costs less
than loading numba; this kernel serves long ones.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

LANES = 4


@numba.njit(cache=True, nogil=True)
def accumulate(
    y_true: NDArray[np.uint8], y_pred: NDArray[np.uint8], counts: NDArray[np.int64]
) -> None:  # pragma: no cover - compiled
    # Hot path, hand-written: sklearn's confusion_matrix runs at ~40 M pairs/s, np.bincount
    # on t * (n + 1) + p at ~300 M/s (it widens to intp first). Labels come in long runs of
    # one class, so a single counter array stalls on store-to-load dependencies; four
    # interleaved lanes (summed in compute) let consecutive equal pairs hit different cells.
    n = y_true.shape[0]
    m = n - n % LANES
    for i in range(0, m, LANES):
        counts[0, y_true[i], y_pred[i]] += 1
        counts[1, y_true[i + 1], y_pred[i + 1]] += 1
        counts[2, y_true[i + 2], y_pred[i + 2]] += 1
        counts[3, y_true[i + 3], y_pred[i + 3]] += 1
    for i in range(m, n):
        counts[0, y_true[i], y_pred[i]] += 1
