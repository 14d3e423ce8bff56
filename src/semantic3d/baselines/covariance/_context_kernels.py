"""Compiled bookkeeping of the context step: the k-NN graph's edges and each expansion move's
graph capacities.

Hand-written because the numpy expressions they replace made ~15 passes over the edge
arrays per move (fancy indexing, three ``bincount``\\ s, temporaries) and an
``(n * (k + 1), k + 1)`` comparison table for the edges; together they cost more than the
max-flow itself. Each kernel is one or two passes and adds in the same order as the numpy
code did, so the capacities (and hence the cuts and labels) are the same floats.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def undirected_edges(neighbours: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``(n_edges, 2)`` int64 pairs ``(min, max)`` from ``(n, k)`` neighbour lists that may
    hold the point itself: ``(i, j)`` is kept from ``i``'s list when ``i < j`` or when
    ``i`` is not in ``j``'s list (each undirected edge once), in row-major list order."""
    n, k = neighbours.shape
    out = np.empty((n * k, 2), np.int64)
    count = 0
    for i in range(n):
        for slot in range(k):
            j = np.int64(neighbours[i, slot])
            if j == i:
                continue
            keep = True
            if j < i:
                for other in range(k):
                    if neighbours[j, other] == i:
                        keep = False
                        break
            if keep:
                out[count, 0] = min(i, j)
                out[count, 1] = max(i, j)
                count += 1
    return out[:count].copy()


@nb.njit(cache=True, nogil=True)
def expansion_capacities(
    unary: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    current: np.ndarray,
    alpha: int,
    weight: float,
    to_source: np.ndarray,
    to_sink: np.ndarray,
    pair: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Capacities of the binary graph of one alpha-expansion move (x = 1 takes ``alpha``).

    Node ``i`` keeps its label at cost ``cost0 = unary[i, current[i]] + sum of the edges
    (i, j) whose labels differ`` and takes ``alpha`` at ``cost1 = unary[i, alpha] +
    sum_(i, j) [alpha != current[j]] - sum_(j, i) [alpha != current[j]]`` (times
    ``weight``); the terminal capacities are ``cost1 - low`` and ``cost0 - low`` with
    ``low = min(cost0, cost1)``, and each edge gets ``b + c - a`` (Kolmogorov & Zabih's
    decomposition of the pairwise term, see ``alpha_expansion``).
    """
    n = unary.shape[0]
    keep_sum = np.zeros(n, np.float64)
    out_sum = np.zeros(n, np.float64)
    in_sum = np.zeros(n, np.float64)
    for e in range(first.size):
        i = first[e]
        j = second[e]
        li = current[i]
        lj = current[j]
        a = weight if li != lj else 0.0
        b = weight if li != alpha else 0.0
        c = weight if alpha != lj else 0.0
        keep_sum[i] += a
        out_sum[i] += c
        in_sum[j] += c
        pair[e] = b + c - a
    for i in range(n):
        cost0 = unary[i, current[i]] + keep_sum[i]
        cost1 = unary[i, alpha] + (out_sum[i] - in_sum[i])
        low = min(cost0, cost1)
        to_source[i] = cost1 - low
        to_sink[i] = cost0 - low


@nb.njit(cache=True, nogil=True)
def count_cut_edges(
    first: np.ndarray, second: np.ndarray, labels: np.ndarray
) -> int:  # pragma: no cover - compiled
    """Edges whose two ends have different labels."""
    count = 0
    for e in range(first.size):
        if labels[first[e]] != labels[second[e]]:
            count += 1
    return count
