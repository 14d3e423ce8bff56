"""Compiled kernels of the level-of-detail build (numba).

Hand-written: the build touches every point at least four times (bounds, cell histogram,
node sizes, writing), and the numpy version (Morton keys bit by bit, ``np.unique`` merges,
``searchsorted`` per depth, ``argsort`` per chunk) ran at 0.6 M points/s. Each pass here
is one loop over a block without temporaries. The octree's cell counts are dense
Morton-ordered blocks of levels (``8**d`` cells ``d`` levels below a block's root, all its
levels in one array at ``level_offset(d)``): the dense top block over the whole cube, and
small blocks refining its over-full bottom cells (and theirs), so finding a point's node
is a few array reads per depth.

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
def _level_offset(depth):  # type: ignore[no-untyped-def]
    return ((1 << (3 * depth)) - 1) // 7


@nb.njit(cache=True, nogil=True, inline="always")
def _cell(v, cube_min, scale, top):  # type: ignore[no-untyped-def]
    """The cell coordinate of ``v`` along one axis (clamped to the grid)."""
    return min(max(int(np.floor((v - cube_min) * scale)), 0), top)


@nb.njit(cache=True, nogil=True, inline="always")
def _leaf_key(x, y, z, cube_min, scale, top, spread):  # type: ignore[no-untyped-def]
    cx = _cell(x, cube_min[0], scale, top)
    cy = _cell(y, cube_min[1], scale, top)
    cz = _cell(z, cube_min[2], scale, top)
    # x highest of each triple, as the octree's child index (x << 2 | y << 1 | z).
    return (spread[cx] << 2) | (spread[cy] << 1) | spread[cz]


@nb.njit(cache=True, nogil=True)
def histogram(xyz, cube_min, scale, top, spread, leaf_counts):  # type: ignore[no-untyped-def]
    """Add each point of a block to the count of its leaf cell."""
    for i in range(xyz.shape[0]):
        key = _leaf_key(xyz[i, 0], xyz[i, 1], xyz[i, 2], cube_min, scale, top, spread)
        leaf_counts[key] += 1


@nb.njit(cache=True, nogil=True, inline="always")
def _mix(index, salt):  # type: ignore[no-untyped-def]
    """splitmix64 of a scan position."""
    z = np.uint64(index) + np.uint64(salt)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@nb.njit(cache=True, nogil=True, inline="always")
def _rank(index):  # type: ignore[no-untyped-def]
    z = _mix(index, 0x9E3779B97F4A7C15)
    return float(z >> np.uint64(11)) / 9007199254740992.0  # 2**53


HASH_SALT = 0xD1B54A32D192ED03
"""Salt of the hash whose bits choose a point's child below the position depth."""


_CHUNK = 1024
"""Points a kernel below takes at a time: first the cells of the dense levels' bottom of
every point (independent reads of a 64 MB array, which the processor overlaps), then each
point's walk."""


@nb.njit(cache=True, nogil=True, inline="always")
def _fine_cells(xyz, p, cube_min, fine_scale, fine_top, cells, j):  # type: ignore[no-untyped-def]
    """Cell coordinates of point ``p`` at the position depth, into ``cells[j]``.

    A cell at a coarser depth ``d`` is ``cells >> (position_depth - d)``: the same as
    ``floor((x - cube_min) * 2**d / cube_size)``, since the scales differ by powers of two.
    """
    for k in range(3):
        cells[j, k] = _cell(xyz[p, k], cube_min[k], fine_scale, fine_top)


@nb.njit(cache=True, nogil=True, inline="always")
def _block_key(  # type: ignore[no-untyped-def]
    cells, j, index, depth, levels, block_cell, b, spread, position_depth
):
    """Morton key of a point's cell ``levels`` below a block's root cell (at ``depth``).

    Above ``position_depth`` the cells are the octants of the cube (``block_cell[b]``: the
    root's integer coordinates; ``cells[j]`` the point's at the position depth); from it
    down, each level's child index is 3 bits of a hash of the point's scan position (the
    points of a cell too small to split by position).
    """
    if depth < position_depth:
        shift = position_depth - depth - levels
        span = (1 << levels) - 1
        cx = min(max((cells[j, 0] >> shift) - (block_cell[b, 0] << levels), 0), span)
        cy = min(max((cells[j, 1] >> shift) - (block_cell[b, 1] << levels), 0), span)
        cz = min(max((cells[j, 2] >> shift) - (block_cell[b, 2] << levels), 0), span)
        return (spread[cx] << 2) | (spread[cy] << 1) | spread[cz]
    h = _mix(index, HASH_SALT)
    shift = 3 * (depth - position_depth)
    key = 0
    for level in range(levels):
        key = (key << 3) | int((h >> np.uint64(shift + 3 * level)) & np.uint64(7))
    return key


@nb.njit(cache=True, nogil=True, inline="always")
def _gather_dense(  # type: ignore[no-untyped-def]
    xyz, c0, m, cube_min, fine_scale, fine_top, spread, shift, bottom, dense_counts,
    dense_ids, cells, keys, bottom_counts, bottom_ids,
):  # fmt: skip
    """Cells, dense bottom keys and the bottom cells' counts and ids of a chunk's points."""
    for j in range(m):
        _fine_cells(xyz, c0 + j, cube_min, fine_scale, fine_top, cells, j)
        key = (
            (spread[cells[j, 0] >> shift] << 2)
            | (spread[cells[j, 1] >> shift] << 1)
            | spread[cells[j, 2] >> shift]
        )
        keys[j] = key
        bottom_counts[j] = dense_counts[bottom + key]
        bottom_ids[j] = dense_ids[bottom + key]


@nb.njit(cache=True, nogil=True)
def refine_histogram(  # type: ignore[no-untyped-def]
    xyz, first_index, cube_min, scales, spread, position_depth, dense_counts, dense_ids,
    counts, ids, block_offset, block_depth, block_levels, block_cell, first_new, boxes,
):  # fmt: skip
    """Count the points of the blocks from ``first_new`` on in their bottom cells.

    A point walks down the blocks: from a block's bottom cell to the block that refines it
    (``ids[cell] = -2 - block``). Points ending in a new block are counted, and their
    cell coordinates at ``position_depth`` grow the block's box ``boxes[block]``
    (min xyz, max xyz) while the block is above that depth.
    """
    fine_scale = scales[position_depth]
    fine_top = (1 << position_depth) - 1
    dense = block_levels[0]
    bottom = _level_offset(dense)
    shift = position_depth - dense
    cells = np.empty((_CHUNK, 3), np.int64)
    keys = np.empty(_CHUNK, np.int64)
    bottom_counts = np.empty(_CHUNK, np.int64)
    bottom_ids = np.empty(_CHUNK, np.int64)
    n = xyz.shape[0]
    for c0 in range(0, n, _CHUNK):
        m = min(_CHUNK, n - c0)
        _gather_dense(
            xyz, c0, m, cube_min, fine_scale, fine_top, spread, shift, bottom, dense_counts,
            dense_ids, cells, keys, bottom_counts, bottom_ids,
        )  # fmt: skip
        for j in range(m):
            child = bottom_ids[j]
            if child > -2:
                continue
            at = 0
            while True:
                b = -2 - child
                levels = block_levels[b]
                key = _block_key(
                    cells, j, first_index + c0 + j, block_depth[b], levels, block_cell, b,
                    spread, position_depth,
                )  # fmt: skip
                at = block_offset[b] + _level_offset(levels) + key
                child = ids[at]
                if child > -2:
                    break
            if b < first_new:
                continue
            counts[at] += 1
            if block_depth[b] < position_depth:
                for k in range(3):
                    boxes[b, k] = min(boxes[b, k], cells[j, k])
                    boxes[b, 3 + k] = max(boxes[b, 3 + k], cells[j, k])


@nb.njit(cache=True, nogil=True)
def assign(  # type: ignore[no-untyped-def]
    xyz, first_index, cube_min, scales, spread, position_depth, dense_counts, dense_ids,
    counts, ids, block_offset, block_depth, block_levels, block_cell, block_node, capacity,
    out,
):  # fmt: skip
    """Node id of each point of a block (the first node on its path that keeps it).

    The first node ``n`` where ``rank * count(n) < capacity``: counts shrink along a path,
    so a block's bottom cell tells whether the point stays in the block (then the walk
    goes up while the rank still passes), or goes on to the block refining that cell
    (``ids[cell] = -2 - block``, whose node is ``block_node[block]``; a block's root has
    its parent cell's count, so the walk resumes one level below it). A cell holding at
    most ``capacity`` points passes every rank (``rank < 1``).
    """
    fine_scale = scales[position_depth]
    fine_top = (1 << position_depth) - 1
    dense = block_levels[0]
    bottom = _level_offset(dense)
    shift = position_depth - dense
    cells = np.empty((_CHUNK, 3), np.int64)
    keys = np.empty(_CHUNK, np.int64)
    bottom_counts = np.empty(_CHUNK, np.int64)
    bottom_ids = np.empty(_CHUNK, np.int64)
    n = xyz.shape[0]
    for c0 in range(0, n, _CHUNK):
        m = min(_CHUNK, n - c0)
        _gather_dense(
            xyz, c0, m, cube_min, fine_scale, fine_top, spread, shift, bottom, dense_counts,
            dense_ids, cells, keys, bottom_counts, bottom_ids,
        )  # fmt: skip
        for j in range(m):
            index = first_index + c0 + j
            r = _rank(index)
            v = bottom_ids[j]
            if r * bottom_counts[j] < capacity:  # in the dense levels: the shallowest
                key = keys[j]
                at = bottom + key
                level = dense
                while level > 0:
                    above = _level_offset(level - 1) + (key >> (3 * (dense - level + 1)))
                    if not r * dense_counts[above] < capacity:
                        break
                    level -= 1
                    at = above
                if level != dense:
                    v = dense_ids[at]
                out[c0 + j] = block_node[-2 - v] if v <= -2 else v
                continue
            while v <= -2:  # below the dense levels, from block to block
                b = -2 - v
                levels = block_levels[b]
                key = _block_key(
                    cells, j, index, block_depth[b], levels, block_cell, b, spread,
                    position_depth,
                )  # fmt: skip
                base = block_offset[b]
                at = base + _level_offset(levels) + key
                v = ids[at]
                if r * counts[at] < capacity:
                    level = levels
                    while level > 1:
                        above = (
                            base + _level_offset(level - 1) + (key >> (3 * (levels - level + 1)))
                        )
                        if not r * counts[above] < capacity:
                            break
                        level -= 1
                        at = above
                    if level != levels:
                        v = ids[at]
                    if v <= -2:
                        v = block_node[-2 - v]
                    break
            out[c0 + j] = v


@nb.njit(cache=True, nogil=True)
def sum_levels(counts, offset, levels):  # type: ignore[no-untyped-def]
    """Fill the levels of a block above its bottom with the sums of their children."""
    for level in range(levels - 1, -1, -1):
        start = offset + _level_offset(level)
        finer = offset + _level_offset(level + 1)
        for k in range(1 << (3 * level)):
            total = 0
            for child in range(8):
                total += counts[finer + 8 * k + child]
            counts[start + k] = total


@nb.njit(cache=True, nogil=True)
def count_nodes(node_of, sizes):  # type: ignore[no-untyped-def]
    for i in range(node_of.shape[0]):
        sizes[node_of[i]] += 1


@nb.njit(cache=True, nogil=True)
def group_block(  # type: ignore[no-untyped-def]
    node_of,
    bucket_of,
    n_buckets,
    first_index,
    xyz,
    origin,
    rgb,
    intensity,
    i_low,
    i_scale,
    positions_out,
    rgb_out,
    intensity_out,
    index_out,
    node_out,
    present,
    run_start,
    run_count,
):
    """Counting sort of a block by bucket (a range of nodes); returns how many buckets the
    block touches.

    Fills the output buffers in bucket order, each bucket's points in scan order (float32
    re-centred positions, rgb, stretched intensity, scan index, node) and, per touched
    bucket, its run (``present``, ``run_start``, ``run_count``) in those buffers.
    """
    n = node_of.shape[0]
    counts = np.zeros(n_buckets, np.int64)
    for i in range(n):
        counts[bucket_of[node_of[i]]] += 1
    m = 0
    position = 0
    cursor = np.empty(n_buckets, np.int64)
    for bucket in range(n_buckets):
        if counts[bucket] > 0:
            present[m] = bucket
            run_start[m] = position
            run_count[m] = counts[bucket]
            m += 1
        cursor[bucket] = position
        position += counts[bucket]
    for i in range(n):
        node = node_of[i]
        j = cursor[bucket_of[node]]
        cursor[bucket_of[node]] = j + 1
        for k in range(3):
            positions_out[j, k] = np.float32(xyz[i, k] - origin[k])
            rgb_out[j, k] = rgb[i, k]
        v = (intensity[i] - i_low) * i_scale
        intensity_out[j] = np.uint8(min(max(v, 0.0), 255.0))
        index_out[j] = first_index + i
        node_out[j] = node
    return m


@nb.njit(cache=True, nogil=True)
def sort_bucket(  # type: ignore[no-untyped-def]
    node_in, first_node, n_nodes, positions_in, rgb_in, intensity_in, index_in,
    positions_out, rgb_out, intensity_out, index_out,
):  # fmt: skip
    """Stable counting sort of a bucket's points by node (nodes ``first_node`` onwards)."""
    cursor = np.zeros(n_nodes + 1, np.int64)
    for i in range(node_in.shape[0]):
        cursor[node_in[i] - first_node + 1] += 1
    for k in range(n_nodes):
        cursor[k + 1] += cursor[k]
    for i in range(node_in.shape[0]):
        local = node_in[i] - first_node
        j = cursor[local]
        cursor[local] = j + 1
        for k in range(3):
            positions_out[j, k] = positions_in[i, k]
            rgb_out[j, k] = rgb_in[i, k]
        intensity_out[j] = intensity_in[i]
        index_out[j] = index_in[i]
