"""Compiled kernels of the level-of-detail build (numba).

Hand-written: the build touches every point four times (bounds, cell histogram, node
sizes, writing), and the numpy version (Morton keys bit by bit, ``np.unique`` merges,
``searchsorted`` per depth, ``argsort`` per chunk) ran at 0.6 M points/s. Each pass here
is one loop over a block without temporaries; the octree levels are dense Morton-ordered
arrays (``8**d`` cells at depth ``d``, all depths in one array at ``level_offset(d)``), so
finding a point's node is a few array reads per depth.

Every point draws a rank in [0, 1) from a hash of its position in the scan (splitmix64), so
the result does not depend on how the scan is cut into blocks.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_SPREAD = np.zeros(256, np.int64)
for _value in range(256):
    _spread = 0
    for _bit in range(8):
        _spread |= ((_value >> _bit) & 1) << (3 * _bit)
    _SPREAD[_value] = _spread


def level_offset(depth: int) -> int:
    """Index of the first cell of depth ``depth`` in the flattened levels (sum of 8**d)."""
    return ((1 << (3 * depth)) - 1) // 7


@nb.njit(cache=True, nogil=True)
def bounds(xyz, intensity, low, high, i_range):  # type: ignore[no-untyped-def]
    """Grow ``low``/``high`` (3,) and ``i_range`` (2,) with a block."""
    for i in range(xyz.shape[0]):
        for k in range(3):
            v = xyz[i, k]
            if v < low[k]:
                low[k] = v
            if v > high[k]:
                high[k] = v
        t = intensity[i]
        if t < i_range[0]:
            i_range[0] = t
        if t > i_range[1]:
            i_range[1] = t


@nb.njit(cache=True, nogil=True, inline="always")
def _leaf_key(x, y, z, cube_min, scale, top, spread):  # type: ignore[no-untyped-def]
    cx = int(np.floor((x - cube_min[0]) * scale))
    cy = int(np.floor((y - cube_min[1]) * scale))
    cz = int(np.floor((z - cube_min[2]) * scale))
    cx = min(max(cx, 0), top)
    cy = min(max(cy, 0), top)
    cz = min(max(cz, 0), top)
    # x highest of each triple, as the octree's child index (x << 2 | y << 1 | z).
    return (spread[cx] << 2) | (spread[cy] << 1) | spread[cz]


@nb.njit(cache=True, nogil=True)
def histogram(xyz, cube_min, scale, top, spread, leaf_counts):  # type: ignore[no-untyped-def]
    """Add each point of a block to the count of its leaf cell."""
    for i in range(xyz.shape[0]):
        key = _leaf_key(xyz[i, 0], xyz[i, 1], xyz[i, 2], cube_min, scale, top, spread)
        leaf_counts[key] += 1


@nb.njit(cache=True, nogil=True, inline="always")
def _rank(index):  # type: ignore[no-untyped-def]
    z = np.uint64(index) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) / 9007199254740992.0  # 2**53


@nb.njit(cache=True, nogil=True)
def assign(  # type: ignore[no-untyped-def]
    xyz, first_index, cube_min, scale, top, spread, depth, counts, ids, offsets, capacity, out
):
    """Node id of each point of a block (the first node on its path that keeps it)."""
    for i in range(xyz.shape[0]):
        leaf = _leaf_key(xyz[i, 0], xyz[i, 1], xyz[i, 2], cube_min, scale, top, spread)
        r = _rank(first_index + i)
        node = -1
        for d in range(depth + 1):
            at = offsets[d] + (leaf >> (3 * (depth - d)))
            c = counts[at]
            if d == depth or c <= capacity or r * c < capacity:
                node = ids[at]
                break
        out[i] = node


@nb.njit(cache=True, nogil=True)
def count_nodes(node_of, sizes):  # type: ignore[no-untyped-def]
    for i in range(node_of.shape[0]):
        sizes[node_of[i]] += 1


@nb.njit(cache=True, nogil=True)
def group_block(  # type: ignore[no-untyped-def]
    node_of,
    first_index,
    xyz,
    origin,
    rgb,
    intensity,
    i_low,
    i_scale,
    n_nodes,
    positions_out,
    rgb_out,
    intensity_out,
    index_out,
    present,
    run_start,
    run_count,
):
    """Counting sort of a block by node; returns how many nodes the block touches.

    Fills the output buffers in node order (float32 re-centred positions, rgb, stretched
    intensity, scan index) and, per touched node, its run (``present``, ``run_start``,
    ``run_count``) in those buffers.
    """
    n = node_of.shape[0]
    counts = np.zeros(n_nodes, np.int64)
    for i in range(n):
        counts[node_of[i]] += 1
    m = 0
    position = 0
    cursor = np.empty(n_nodes, np.int64)
    for node in range(n_nodes):
        if counts[node] > 0:
            present[m] = node
            run_start[m] = position
            run_count[m] = counts[node]
            m += 1
        cursor[node] = position
        position += counts[node]
    for i in range(n):
        j = cursor[node_of[i]]
        cursor[node_of[i]] = j + 1
        for k in range(3):
            positions_out[j, k] = np.float32(xyz[i, k] - origin[k])
            rgb_out[j, k] = rgb[i, k]
        v = (intensity[i] - i_low) * i_scale
        intensity_out[j] = np.uint8(min(max(v, 0.0), 255.0))
        index_out[j] = first_index + i
    return m
