"""Compiled minimum cut (Boykov-Kolmogorov) and the alpha-expansion loop of the context step.

Hand-written because PyMaxflow, the library that wraps the same algorithm, holds the GIL
while it cuts and is fed through Python calls per move: with two scans labelled at once on
two threads, its cuts ran one at a time, and building its graph (nodes, terminal and edge
capacities, ~3 Python-level array passes per move) cost a third as much as the cut itself.
Here the graph of a tile is laid out once (arcs in compressed rows), each move only rewrites
the capacities, and the whole loop runs compiled without the GIL.

The search follows Boykov & Kolmogorov, "An experimental comparison of min-cut/max-flow
algorithms for energy minimization in vision" (PAMI 2004), as in Kolmogorov's maxflow
v3: two search trees grown breadth first from the terminals, paths augmented through their
bottleneck, orphans adopted with the distance/time-stamp heuristic. The order of every
choice is the reference implementation's (a node's arcs newest first, active nodes first
in first out, the orphans of an augmentation last found first), so the cuts, and hence the
labels, are those PyMaxflow gives; the tests check both against it.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from semantic3d.baselines.covariance._context_kernels import expansion_arcs

_FREE = -1  # no parent: the node is in neither search tree
_TERMINAL = -2  # the parent is the tree's terminal
_ORPHAN = -3  # the parent arc was saturated; the node waits for adoption
_INFINITE_DISTANCE = 1 << 30


@nb.njit(cache=True, nogil=True, inline="always")
def _wrap(position: int, n: int) -> int:  # pragma: no cover - compiled
    """``position % n`` for ``0 <= position < 2 n`` (the rings' indices), without a division."""
    return position - n if position >= n else position


def index_type(n: int, n_edges: int) -> np.ndarray:
    """An empty array of the integer type that numbers the nodes and arcs of a graph of
    ``n`` nodes and ``n_edges`` edges: int32 where both fit (half the size of the index
    arrays the search reads at random; the cut is the same), else int64."""
    fits = max(n, 2 * n_edges) < np.iinfo(np.int32).max
    return np.empty(0, np.int32 if fits else np.int64)


@nb.njit(cache=True, nogil=True)
def arc_layout(
    n: int, first: np.ndarray, second: np.ndarray, index: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Arcs of the undirected edges ``(first[e], second[e])`` in compressed rows.

    Returns ``(row_start, head, sister, forward, backward)``: the arcs leaving node ``i``
    are ``row_start[i]:row_start[i + 1]`` (newest edge first, as the reference inserts
    them), ``head[a]`` is where arc ``a`` goes and ``sister[a]`` its reverse; edge ``e``'s
    arc from ``first[e]`` is ``forward[e]`` and the one back is ``backward[e]``. All but
    ``row_start`` have ``index``'s integer type (:func:`index_type`).
    """
    m = first.size
    row_start = np.zeros(n + 1, np.int64)
    for e in range(m):
        row_start[first[e] + 1] += 1
        row_start[second[e] + 1] += 1
    for i in range(n):
        row_start[i + 1] += row_start[i]
    fill = row_start[:n].copy()
    head = np.empty(2 * m, index.dtype)
    sister = np.empty(2 * m, index.dtype)
    forward = np.empty(m, index.dtype)
    backward = np.empty(m, index.dtype)
    for e in range(m - 1, -1, -1):
        i = first[e]
        j = second[e]
        a = fill[i]
        fill[i] += 1
        b = fill[j]
        fill[j] += 1
        head[a] = j
        head[b] = i
        sister[a] = b
        sister[b] = a
        forward[e] = a
        backward[e] = b
    return row_start, head, sister, forward, backward


@nb.njit(cache=True, nogil=True)
def max_flow(
    row_start: np.ndarray,
    head: np.ndarray,
    sister: np.ndarray,
    residual: np.ndarray,
    terminal: np.ndarray,
    sink_side: np.ndarray,
) -> float:  # pragma: no cover - compiled
    """Push the maximum flow through the graph; returns its value.

    Args:
        row_start, head, sister: the arcs (:func:`arc_layout`).
        residual: ``(n_arcs,)`` capacity of every arc, left as the residual capacities.
        terminal: ``(n,)`` capacity from the source minus capacity to the sink of every
            node (positive: joined to the source), left as the residual.
        sink_side: ``(n,)`` output, True for the nodes on the sink's side of a minimum cut
            (those the sink's search tree holds at the end; the others, including nodes in
            no tree, are on the source's side).
    """
    n = terminal.size
    # node and arc numbers in the arcs' integer type (int32 for any tile: less to fetch)
    parent = np.empty(n, head.dtype)
    in_sink_tree = np.zeros(n, np.bool_)
    stamp = np.zeros(n, np.int64)
    distance = np.ones(n, head.dtype)
    queued = np.zeros(n, np.bool_)
    # active nodes, first in first out (a ring: a node is queued at most once at a time)
    queue = np.empty(max(n, 1), head.dtype)
    queue_head = 0
    queue_size = 0
    # orphans of one augmentation (taken last found first) and of one adoption cascade
    # (first in first out, a ring: an orphan is queued at most once at a time)
    found_orphans = np.empty(max(n, 1), head.dtype)
    n_found = 0
    cascade = np.empty(max(n, 1), head.dtype)

    for i in range(n):
        if terminal[i] > 0 or terminal[i] < 0:
            in_sink_tree[i] = terminal[i] < 0
            parent[i] = _TERMINAL
            queued[i] = True
            queue[_wrap(queue_head + queue_size, n)] = i
            queue_size += 1
        else:
            parent[i] = _FREE

    flow = 0.0
    time = 0
    current = -1
    while True:
        # --- the next active node: the one that found a path, while it has a parent
        i = -1
        if current >= 0:
            queued[current] = False
            if parent[current] != _FREE:
                i = current
        if i < 0:
            while queue_size > 0:
                candidate = queue[queue_head]
                queue_head = _wrap(queue_head + 1, n)
                queue_size -= 1
                queued[candidate] = False
                if parent[candidate] != _FREE:
                    i = candidate
                    break
            if i < 0:
                break

        # --- growth: extend i's tree through its arcs until the trees touch
        middle = -1
        if not in_sink_tree[i]:
            for a in range(row_start[i], row_start[i + 1]):
                if residual[a] != 0.0:
                    j = head[a]
                    if parent[j] == _FREE:
                        in_sink_tree[j] = False
                        parent[j] = sister[a]
                        stamp[j] = stamp[i]
                        distance[j] = distance[i] + 1
                        if not queued[j]:
                            queued[j] = True
                            queue[_wrap(queue_head + queue_size, n)] = j
                            queue_size += 1
                    elif in_sink_tree[j]:
                        middle = a
                        break
                    elif stamp[j] <= stamp[i] and distance[j] > distance[i]:
                        parent[j] = sister[a]
                        stamp[j] = stamp[i]
                        distance[j] = distance[i] + 1
        else:
            for a in range(row_start[i], row_start[i + 1]):
                if residual[sister[a]] != 0.0:
                    j = head[a]
                    if parent[j] == _FREE:
                        in_sink_tree[j] = True
                        parent[j] = sister[a]
                        stamp[j] = stamp[i]
                        distance[j] = distance[i] + 1
                        if not queued[j]:
                            queued[j] = True
                            queue[_wrap(queue_head + queue_size, n)] = j
                            queue_size += 1
                    elif not in_sink_tree[j]:
                        middle = sister[a]
                        break
                    elif stamp[j] <= stamp[i] and distance[j] > distance[i]:
                        parent[j] = sister[a]
                        stamp[j] = stamp[i]
                        distance[j] = distance[i] + 1
        time += 1
        if middle < 0:
            current = -1
            continue
        queued[i] = True  # stays the current node: not queued again meanwhile
        current = i

        # --- augmentation along source ... tail -> middle -> head ... sink
        bottleneck = residual[middle]
        k = head[sister[middle]]
        while parent[k] != _TERMINAL:
            a = parent[k]
            if bottleneck > residual[sister[a]]:
                bottleneck = residual[sister[a]]
            k = head[a]
        if bottleneck > terminal[k]:
            bottleneck = terminal[k]
        k = head[middle]
        while parent[k] != _TERMINAL:
            a = parent[k]
            if bottleneck > residual[a]:
                bottleneck = residual[a]
            k = head[a]
        if bottleneck > -terminal[k]:
            bottleneck = -terminal[k]

        residual[sister[middle]] += bottleneck
        residual[middle] -= bottleneck
        k = head[sister[middle]]
        while parent[k] != _TERMINAL:
            a = parent[k]
            residual[a] += bottleneck
            residual[sister[a]] -= bottleneck
            if residual[sister[a]] == 0.0:
                parent[k] = _ORPHAN
                found_orphans[n_found] = k
                n_found += 1
            k = head[a]
        terminal[k] -= bottleneck
        if terminal[k] == 0.0:
            parent[k] = _ORPHAN
            found_orphans[n_found] = k
            n_found += 1
        k = head[middle]
        while parent[k] != _TERMINAL:
            a = parent[k]
            residual[sister[a]] += bottleneck
            residual[a] -= bottleneck
            if residual[a] == 0.0:
                parent[k] = _ORPHAN
                found_orphans[n_found] = k
                n_found += 1
            k = head[a]
        terminal[k] += bottleneck
        if terminal[k] == 0.0:
            parent[k] = _ORPHAN
            found_orphans[n_found] = k
            n_found += 1
        flow += bottleneck

        # --- adoption: each orphan of the augmentation, then the orphans it makes
        while n_found > 0:
            n_found -= 1
            cascade[0] = found_orphans[n_found]
            cascade_head = 0
            cascade_size = 1
            while cascade_size > 0:
                o = cascade[cascade_head]
                cascade_head = _wrap(cascade_head + 1, n)
                cascade_size -= 1
                sink = in_sink_tree[o]
                best = -1
                best_distance = _INFINITE_DISTANCE
                for a0 in range(row_start[o], row_start[o + 1]):
                    # an arc that can carry flow between o's would-be parent and o
                    if residual[a0 if sink else sister[a0]] == 0.0:
                        continue
                    j = head[a0]
                    if in_sink_tree[j] != sink or parent[j] == _FREE:
                        continue
                    # does j still reach the terminal? (stamps cache the answer)
                    d = 0
                    k = j
                    while True:
                        if stamp[k] == time:
                            d += distance[k]
                            break
                        a = parent[k]
                        d += 1
                        if a == _TERMINAL:
                            stamp[k] = time
                            distance[k] = 1
                            break
                        if a == _ORPHAN:
                            d = _INFINITE_DISTANCE
                            break
                        k = head[a]
                    if d < _INFINITE_DISTANCE:
                        if d < best_distance:
                            best = a0
                            best_distance = d
                        k = j
                        while stamp[k] != time:
                            stamp[k] = time
                            distance[k] = d
                            d -= 1
                            k = head[parent[k]]
                if best >= 0:
                    parent[o] = best
                    stamp[o] = time
                    distance[o] = best_distance + 1
                    continue
                parent[o] = _FREE
                for a0 in range(row_start[o], row_start[o + 1]):
                    j = head[a0]
                    if in_sink_tree[j] != sink or parent[j] == _FREE:
                        continue
                    a = parent[j]
                    if residual[a0 if sink else sister[a0]] != 0.0 and not queued[j]:
                        queued[j] = True
                        queue[_wrap(queue_head + queue_size, n)] = j
                        queue_size += 1
                    if a != _TERMINAL and a != _ORPHAN and head[a] == o:
                        parent[j] = _ORPHAN
                        cascade[_wrap(cascade_head + cascade_size, n)] = j
                        cascade_size += 1

    for i in range(n):
        sink_side[i] = parent[i] != _FREE and in_sink_tree[i]
    return flow


@nb.njit(cache=True, nogil=True)
def expand_labels(
    unary: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    labels: np.ndarray,
    weight: float,
    max_sweeps: int,
    index: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """Alpha-expansion of ``labels`` (``(n,)`` int64 columns of ``unary``) under the Potts
    energy ``sum unary[i, l_i] + weight * (edges whose ends differ)``; see
    :func:`~semantic3d.baselines.covariance.context.alpha_expansion`, which checks the
    arguments. A move is kept when it lowers the energy by more than 1e-9. ``index``: an
    empty array of the graph's index type (:func:`index_type`)."""
    n, n_labels = unary.shape
    m = first.size
    current = labels.copy()
    row_start, head, sister, forward, backward = arc_layout(n, first, second, index)
    residual = np.empty(2 * m, np.float64)
    terminal = np.empty(n, np.float64)
    take = np.empty(n, np.bool_)
    for _ in range(max_sweeps):
        changed = False
        for alpha in range(n_labels):
            expansion_arcs(
                unary, first, second, current, alpha, weight, terminal, forward, backward, residual
            )
            max_flow(row_start, head, sister, residual, terminal, take)
            # the energy change of the move, exactly as a difference of its two terms
            data = 0.0
            for i in range(n):
                if take[i] and current[i] != alpha:
                    data += unary[i, alpha] - unary[i, current[i]]
            cut_change = 0
            for e in range(m):
                i = first[e]
                j = second[e]
                before = current[i] != current[j]
                li = alpha if take[i] else current[i]
                lj = alpha if take[j] else current[j]
                cut_change += (li != lj) - before
            if data + weight * cut_change < -1e-9:
                for i in range(n):
                    if take[i]:
                        current[i] = alpha
                changed = True
        if not changed:
            break
    return current
