"""Eigen features of k-nearest-neighbour covariances (Hackel et al. 2016, table 1).

For a query point ``p`` with neighbours ``p_1..p_k`` (in canonical order, see
:mod:`semantic3d.features.neighbourhoods`), the covariance ``C = 1/k Σ (p_i - m)(p_i - m)ᵀ``
(``m`` the neighbours' mean) has eigenvalues ``λ1 ≥ λ2 ≥ λ3 ≥ 0`` and eigenvectors
``e1, e2, e3``; ``ε_i = λ_i / Σλ`` are the normalised eigenvalues. Columns, in
:data:`~semantic3d.features.names.COVARIANCE_FEATURES` + ``MOMENT_FEATURES`` order:

============================  =======================================
sum_of_eigenvalues            ``λ1 + λ2 + λ3``
omnivariance                  ``(ε1 ε2 ε3)^(1/3)``
eigenentropy                  ``-Σ ε_i ln ε_i`` (``0 ln 0 = 0``)
anisotropy                    ``(λ1 - λ3) / λ1``
planarity                     ``(λ2 - λ3) / λ1``
linearity                     ``(λ1 - λ2) / λ1``
surface_variation             ``λ3 / Σλ``
sphericity                    ``λ3 / λ1``
verticality                   ``1 - |e3 · [0 0 1]|``
moment1_axis1, moment1_axis2  ``|Σ (p_i - p) · e1|``, ``|Σ (p_i - p) · e2|``
moment2_axis1, moment2_axis2  ``Σ ((p_i - p) · e1)²``, ``Σ ((p_i - p) · e2)²``
============================  =======================================

A neighbourhood whose spread is below ``1e-8`` m (``Σλ ≤ 1e-16`` m², e.g. duplicate points
or a single voxel at a coarse level) has no shape: every column is 0.

The height kernel of :mod:`semantic3d.features.height` is here too: ``geometry_kernel``,
the per-level pass of the multi-scale features, inlines the covariance row and the height
row, so one read of the neighbours gives the 13 columns above and the 3 height columns.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.atomic import row_workers, take_row_block
from semantic3d.core.errors import ShapeError
from semantic3d.features.names import COVARIANCE_FEATURES, MOMENT_FEATURES

_BLOCK_ROWS = 512  # rows a thread takes at a time in the row kernels

N_COVARIANCE_COLUMNS = len(COVARIANCE_FEATURES) + len(MOMENT_FEATURES)

DEGENERATE_SUM_M2 = 1e-16
"""Neighbourhoods with ``Σλ`` at or below this (m²) are treated as shapeless points."""

_MAX_SWEEPS = 32
_SEPARATION = 1e-3
"""Relative eigenvalue gap below which the closed form hands over to Jacobi."""


def compute_covariance_features(
    points: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    queries: NDArray[np.float64],
) -> NDArray[np.float32]:
    """Covariance and moment features of every query.

    Args:
        points: ``(n, 3)`` float64 candidate neighbours (one pyramid level).
        neighbours: ``(m, k)`` integer (int64 or uint32) rows of indices into ``points``.
        queries: ``(m, 3)`` float64 query points, in the same frame as ``points``.

    Returns:
        ``(m, 13)`` float32 columns in ``COVARIANCE_FEATURES + MOMENT_FEATURES`` order.
    """
    indices = _check_inputs(points, neighbours, queries)
    out = np.empty((indices.shape[0], N_COVARIANCE_COLUMNS), np.float32)
    geometry_kernel(points, indices, queries, out, False, numba.get_num_threads())
    return out


def as_kernel_indices(neighbours: NDArray[np.integer], n_points: int) -> NDArray[np.integer]:
    """Checked ``neighbours`` in the one index type the kernels are compiled for.

    The neighbour searches give C-contiguous uint32; other integer arrays (a k-d tree's
    int64, say) are converted, so a caller's dtype never costs another compilation of
    the kernels (~10 s each). Indices must lie in ``0..n_points - 1``; int64 is kept only
    where uint32 cannot hold them.
    """
    if neighbours.ndim != 2 or neighbours.shape[1] < 1 or neighbours.dtype.kind not in "iu":
        raise ShapeError(
            f"neighbours: expected (m, k) integers with k >= 1, found "
            f"{neighbours.shape} {neighbours.dtype}"
        )
    if neighbours.size and (neighbours.min() < 0 or neighbours.max() >= n_points):
        raise ShapeError(f"neighbours: expected indices in 0..{n_points - 1}")
    dtype = np.uint32 if n_points <= np.iinfo(np.uint32).max else np.int64
    return np.ascontiguousarray(neighbours, dtype=dtype)


def compute_eigen(
    covariances: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Eigenvalues (descending) and eigenvectors (columns) of ``(m, 3, 3)`` symmetric matrices.

    The compiled solver used by :func:`compute_covariance_features` (closed form, Jacobi
    for near-repeated eigenvalues), exposed for tests and benchmarks; agrees with
    ``np.linalg.eigh`` to ~1e-14 relative.
    """
    matrices = np.ascontiguousarray(covariances, dtype=np.float64)
    if matrices.ndim != 3 or matrices.shape[1:] != (3, 3):
        raise ShapeError(f"covariances: expected (m, 3, 3), found {matrices.shape}")
    values = np.empty((matrices.shape[0], 3), np.float64)
    vectors = np.empty((matrices.shape[0], 3, 3), np.float64)
    _eigen_batch(matrices, values, vectors)
    return values, vectors


def _check_inputs(
    points: NDArray[np.float64], neighbours: NDArray[np.integer], queries: NDArray[np.float64]
) -> NDArray[np.integer]:
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype != np.float64:
        raise ShapeError(f"points: expected (n, 3) float64, found {points.shape} {points.dtype}")
    indices = as_kernel_indices(neighbours, points.shape[0])
    if queries.shape != (neighbours.shape[0], 3) or queries.dtype != np.float64:
        raise ShapeError(
            f"queries: expected ({neighbours.shape[0]}, 3) float64, "
            f"found {queries.shape} {queries.dtype}"
        )
    return indices


# Hand-written hot path: millions of 3x3 symmetric eigenproblems per scan. Batched LAPACK
# (np.linalg.eigh on (m, 3, 3)) costs ~1 µs per matrix plus the (m, 3, 3) temporaries.
# The closed form below is ~4x cheaper than Jacobi (measured, CPU time) and handles well
# separated spectra; cyclic Jacobi (3-5 sweeps) stays accurate for repeated eigenvalues
# (linear, isotropic and duplicate-point neighbourhoods). Both fuse with the feature loop.
@numba.njit(cache=True, nogil=True, inline="always")
def _jacobi_eigen(a: NDArray[np.float64], v: NDArray[np.float64]) -> None:  # pragma: no cover
    """Diagonalise the symmetric 3x3 ``a`` in place; ``v`` receives eigenvectors as columns."""
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(_MAX_SWEEPS):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-36 * diag or off == 0.0:
            return
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(3):  # columns p, q of a
                    arp = a[r, p]
                    arq = a[r, q]
                    a[r, p] = c * arp - s * arq
                    a[r, q] = s * arp + c * arq
                for r in range(3):  # rows p, q of a
                    apr = a[p, r]
                    aqr = a[q, r]
                    a[p, r] = c * apr - s * aqr
                    a[q, r] = s * apr + c * aqr
                for r in range(3):
                    vrp = v[r, p]
                    vrq = v[r, q]
                    v[r, p] = c * vrp - s * vrq
                    v[r, q] = s * vrp + c * vrq


@numba.njit(cache=True, nogil=True, inline="always")
def _null_vector(
    a: NDArray[np.float64], value: float, v: NDArray[np.float64], column: int
) -> None:  # pragma: no cover - compiled
    """Unit vector spanning the null space of ``a - value I`` (simple eigenvalue), into
    ``v[:, column]``: the longest cross product of two rows of ``a - value I``."""
    r00, r01, r02 = a[0, 0] - value, a[0, 1], a[0, 2]
    r11, r12, r22 = a[1, 1] - value, a[1, 2], a[2, 2] - value
    c0 = (r01 * r12 - r02 * r11, r02 * r01 - r00 * r12, r00 * r11 - r01 * r01)
    c1 = (r01 * r22 - r02 * r12, r02 * r02 - r00 * r22, r00 * r12 - r01 * r02)
    c2 = (r11 * r22 - r12 * r12, r12 * r02 - r01 * r22, r01 * r12 - r11 * r02)
    n0 = c0[0] * c0[0] + c0[1] * c0[1] + c0[2] * c0[2]
    n1 = c1[0] * c1[0] + c1[1] * c1[1] + c1[2] * c1[2]
    n2 = c2[0] * c2[0] + c2[1] * c2[1] + c2[2] * c2[2]
    best, norm = c0, n0
    if n1 > norm:
        best, norm = c1, n1
    if n2 > norm:
        best, norm = c2, n2
    scale = 1.0 / math.sqrt(norm)
    for r in range(3):
        v[r, column] = best[r] * scale


@numba.njit(cache=True, nogil=True, inline="always")
def _analytic_eigen(
    a: NDArray[np.float64], v: NDArray[np.float64], values: NDArray[np.float64]
) -> bool:  # pragma: no cover - compiled
    """Closed-form eigen-decomposition when the eigenvalues are well separated.

    Eigenvalues by the trigonometric formula (Smith 1961), e1 and e3 as null vectors,
    e2 = e3 x e1. Returns False, touching nothing, when two eigenvalues are within
    ``1e-3`` of the spectrum's spread (null vectors would be inaccurate): Jacobi then.
    """
    q = (a[0, 0] + a[1, 1] + a[2, 2]) / 3.0
    b00 = a[0, 0] - q
    b11 = a[1, 1] - q
    b22 = a[2, 2] - q
    off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
    p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    if not p > 0.0:
        return False
    det = (
        b00 * (b11 * b22 - a[1, 2] * a[1, 2])
        - a[0, 1] * (a[0, 1] * b22 - a[1, 2] * a[0, 2])
        + a[0, 2] * (a[0, 1] * a[1, 2] - b11 * a[0, 2])
    )
    half = min(1.0, max(-1.0, det / (2.0 * p * p * p)))
    phi = math.acos(half) / 3.0
    l1 = q + 2.0 * p * math.cos(phi)
    l3 = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    l2 = 3.0 * q - l1 - l3
    if l1 - l2 <= _SEPARATION * p or l2 - l3 <= _SEPARATION * p:
        return False
    _null_vector(a, l1, v, 0)
    _null_vector(a, l3, v, 2)
    v[0, 1] = v[1, 2] * v[2, 0] - v[2, 2] * v[1, 0]
    v[1, 1] = v[2, 2] * v[0, 0] - v[0, 2] * v[2, 0]
    v[2, 1] = v[0, 2] * v[1, 0] - v[1, 2] * v[0, 0]
    values[0] = max(l1, 0.0)
    values[1] = max(l2, 0.0)
    values[2] = max(l3, 0.0)
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _sorted_eigen(
    a: NDArray[np.float64], v: NDArray[np.float64], values: NDArray[np.float64]
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """Eigen-decompose ``a``; write eigenvalues (descending, clamped at 0) to ``values``.

    Closed form when the spectrum is well separated, cyclic Jacobi otherwise (flat,
    linear, isotropic or duplicate-point neighbourhoods). Returns the columns of ``v``
    holding e1, e2, e3.
    """
    if _analytic_eigen(a, v, values):
        return 0, 1, 2
    _jacobi_eigen(a, v)
    d0 = a[0, 0]
    d1 = a[1, 1]
    d2 = a[2, 2]
    i0, i1, i2 = 0, 1, 2
    if d0 < d1:
        d0, d1 = d1, d0
        i0, i1 = i1, i0
    if d1 < d2:
        d1, d2 = d2, d1
        i1, i2 = i2, i1
    if d0 < d1:
        d0, d1 = d1, d0
        i0, i1 = i1, i0
    values[0] = max(d0, 0.0)
    values[1] = max(d1, 0.0)
    values[2] = max(d2, 0.0)
    return i0, i1, i2


@numba.njit(cache=True, nogil=True, parallel=True)
def _eigen_batch(
    matrices: NDArray[np.float64], values: NDArray[np.float64], vectors: NDArray[np.float64]
) -> None:  # pragma: no cover - compiled
    for m in numba.prange(matrices.shape[0]):
        a = matrices[m].copy()
        v = np.empty((3, 3), np.float64)
        w = np.empty(3, np.float64)
        i0, i1, i2 = _sorted_eigen(a, v, w)
        for r in range(3):
            values[m, r] = w[r]
            vectors[m, r, 0] = v[r, i0]
            vectors[m, r, 1] = v[r, i1]
            vectors[m, r, 2] = v[r, i2]


# Hand-written: one pass over the neighbour indices without an (m, k) gather temporary.
@numba.njit(cache=True, nogil=True, parallel=True)
def height_kernel(
    points: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    queries: NDArray[np.float64],
    out: NDArray[np.float32],
) -> None:  # pragma: no cover - compiled
    """Write the 3 height columns of every query into ``out`` (unchecked inputs; see
    :mod:`semantic3d.features.height`)."""
    for row in numba.prange(neighbours.shape[0]):
        _height_row(points, neighbours, queries, row, out, 0)


# Hand-written: the covariance and moment columns (and, with ``with_height``, the height
# columns) of a level in one parallel pass (one kernel launch per level instead of two).
# It inlines the rows of ``height_kernel``, so its height columns are that kernel's bit for
# bit. The kernels and their row functions stay in this one file: numba's cache does not
# see changes to compiled functions defined in other files.
@numba.njit(cache=True, nogil=True, parallel=True)
def geometry_kernel(
    points: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    queries: NDArray[np.float64],
    out: NDArray[np.float32],
    with_height: bool,
    n_threads: int,
) -> None:  # pragma: no cover - compiled
    """Write the 13 covariance/moment columns (then, ``with_height``, the 3 height
    columns) of every query into ``out`` (unchecked inputs; see above); blocks of rows
    taken as threads come free (a row's eigen-decomposition costs what its neighbourhood
    makes it, and a thread slowed by another process would hold the others at the end of
    equal shares)."""
    n_rows = neighbours.shape[0]
    taken = np.zeros(1, np.int64)
    for _worker in numba.prange(row_workers(n_threads, n_rows, _BLOCK_ROWS)):
        while True:
            start, stop = take_row_block(taken, n_rows, _BLOCK_ROWS)
            if start >= stop:
                break
            for row in range(start, stop):
                _covariance_row(points, neighbours, queries, row, out)
                if with_height:
                    _height_row(points, neighbours, queries, row, out, N_COVARIANCE_COLUMNS)


@numba.njit(cache=True, nogil=True, inline="always")
def _height_row(
    points: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    queries: NDArray[np.float64],
    row: int,
    out: NDArray[np.float32],
    column: int,
) -> None:  # pragma: no cover - compiled
    """The 3 height columns of query ``row`` into ``out[row, column:column + 3]``."""
    low = np.inf
    high = -np.inf
    for j in range(neighbours.shape[1]):
        z = points[neighbours[row, j], 2]
        low = min(low, z)
        high = max(high, z)
    z = queries[row, 2]
    out[row, column] = high - low
    out[row, column + 1] = z - low
    out[row, column + 2] = high - z


@numba.njit(cache=True, nogil=True, inline="always")
def _covariance_row(
    points: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    queries: NDArray[np.float64],
    row: int,
    out: NDArray[np.float32],
) -> None:  # pragma: no cover - compiled
    """The 13 columns of query ``row`` into ``out[row, :13]``."""
    k = neighbours.shape[1]
    qx = queries[row, 0]
    qy = queries[row, 1]
    qz = queries[row, 2]
    # Offsets from the query keep the sums small and exact enough in float64.
    mx = 0.0
    my = 0.0
    mz = 0.0
    for j in range(k):
        idx = neighbours[row, j]
        mx += points[idx, 0] - qx
        my += points[idx, 1] - qy
        mz += points[idx, 2] - qz
    mx /= k
    my /= k
    mz /= k
    a = np.zeros((3, 3), np.float64)
    for j in range(k):
        idx = neighbours[row, j]
        dx = points[idx, 0] - qx - mx
        dy = points[idx, 1] - qy - my
        dz = points[idx, 2] - qz - mz
        a[0, 0] += dx * dx
        a[0, 1] += dx * dy
        a[0, 2] += dx * dz
        a[1, 1] += dy * dy
        a[1, 2] += dy * dz
        a[2, 2] += dz * dz
    for i in range(3):
        for j in range(i, 3):
            a[i, j] /= k
            a[j, i] = a[i, j]
    v = np.empty((3, 3), np.float64)
    w = np.empty(3, np.float64)
    i0, i1, i2 = _sorted_eigen(a, v, w)
    total = w[0] + w[1] + w[2]
    if total <= DEGENERATE_SUM_M2:
        for c in range(N_COVARIANCE_COLUMNS):
            out[row, c] = 0.0
        return
    l1 = w[0]
    e1 = w[0] / total
    e2 = w[1] / total
    e3 = w[2] / total
    entropy = 0.0
    if e1 > 0.0:
        entropy -= e1 * math.log(e1)
    if e2 > 0.0:
        entropy -= e2 * math.log(e2)
    if e3 > 0.0:
        entropy -= e3 * math.log(e3)
    out[row, 0] = total
    out[row, 1] = (e1 * e2 * e3) ** (1.0 / 3.0)
    out[row, 2] = entropy
    out[row, 3] = (w[0] - w[2]) / l1
    out[row, 4] = (w[1] - w[2]) / l1
    out[row, 5] = (w[0] - w[1]) / l1
    out[row, 6] = w[2] / total
    out[row, 7] = w[2] / l1
    out[row, 8] = 1.0 - abs(v[2, i2])
    first1 = 0.0
    first2 = 0.0
    second1 = 0.0
    second2 = 0.0
    for j in range(k):
        idx = neighbours[row, j]
        dx = points[idx, 0] - qx
        dy = points[idx, 1] - qy
        dz = points[idx, 2] - qz
        p1 = dx * v[0, i0] + dy * v[1, i0] + dz * v[2, i0]
        p2 = dx * v[0, i1] + dy * v[1, i1] + dz * v[2, i1]
        first1 += p1
        first2 += p2
        second1 += p1 * p1
        second2 += p2 * p2
    out[row, 9] = abs(first1)
    out[row, 10] = abs(first2)
    out[row, 11] = second1
    out[row, 12] = second2
