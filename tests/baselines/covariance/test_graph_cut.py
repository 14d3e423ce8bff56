"""The compiled minimum cut and alpha-expansion, against PyMaxflow (the same algorithm as a
library) and against the definition of a minimum cut."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.baselines.covariance._context_kernels import expansion_capacities
from semantic3d.baselines.covariance._graph_cut import (
    arc_layout,
    expand_labels,
    index_type,
    max_flow,
)
from semantic3d.baselines.covariance.context import (
    alpha_expansion,
    knn_edges,
    potts_energy,
    unary_costs,
)

maxflow = pytest.importorskip("maxflow")


@st.composite
def graphs(draw: st.DrawFn) -> tuple[np.ndarray, ...]:
    """A random graph: terminal capacities, directed edge pairs with both capacities.
    Whole numbers half of the time, so that cuts of equal capacity (ties) are common."""
    n = draw(st.integers(1, 25))
    m = draw(st.integers(0, 3 * n)) if n > 1 else 0
    seed = draw(st.integers(0, 2**32 - 1))
    whole = draw(st.booleans())
    rng = np.random.default_rng(seed)
    first, second = rng.integers(0, n, m), rng.integers(0, n, m)
    keep = first != second
    first, second = first[keep].astype(np.int64), second[keep].astype(np.int64)
    capacity = rng.random(first.size) * 3 * (rng.random(first.size) < 0.8)
    reverse = rng.random(first.size) * 3 * (rng.random(first.size) < 0.5)
    source = rng.random(n) * 4 * (rng.random(n) < 0.6)
    sink = rng.random(n) * 4 * (rng.random(n) < 0.6)
    if whole:
        capacity, reverse, source, sink = (np.round(a) for a in (capacity, reverse, source, sink))
    return first, second, capacity, reverse, source, sink


def _compiled_cut(
    first: np.ndarray,
    second: np.ndarray,
    capacity: np.ndarray,
    reverse: np.ndarray,
    source: np.ndarray,
    sink: np.ndarray,
    index: np.ndarray,
) -> tuple[float, np.ndarray]:
    n = source.size
    row_start, head, sister, forward, backward = arc_layout(n, first, second, index)
    residual = np.empty(2 * first.size)
    residual[forward], residual[backward] = capacity, reverse
    sink_side = np.empty(n, np.bool_)
    # the part of each node's terminal capacities that cancels flows straight through it
    flow = max_flow(row_start, head, sister, residual, source - sink, sink_side)
    return flow + float(np.minimum(source, sink).sum()), sink_side


@settings(max_examples=300, deadline=None)
@given(graphs())
def test_max_flow_equals_pymaxflow_and_its_cut(graph: tuple[np.ndarray, ...]) -> None:
    first, second, capacity, reverse, source, sink = graph
    flow, sink_side = _compiled_cut(*graph, index_type(source.size, first.size))
    wide = _compiled_cut(*graph, np.empty(0, np.int64))  # graphs too large for int32
    assert wide[0] == flow
    np.testing.assert_array_equal(wide[1], sink_side)

    reference = maxflow.Graph[float](source.size, first.size)
    nodes = reference.add_nodes(source.size)
    reference.add_grid_tedges(nodes, source, sink)
    reference.add_edges(first, second, capacity, reverse)
    expected = reference.maxflow()
    assert flow == pytest.approx(expected, rel=1e-12, abs=1e-12)
    # the same cut, not only one of the same capacity
    np.testing.assert_array_equal(sink_side, reference.get_grid_segments(nodes))

    # and a minimum one: its capacity is the flow (max-flow min-cut theorem)
    cut = source[sink_side].sum() + sink[~sink_side].sum()
    cut += capacity[~sink_side[first] & sink_side[second]].sum()
    cut += reverse[sink_side[first] & ~sink_side[second]].sum()
    assert cut == pytest.approx(flow, rel=1e-9, abs=1e-9)


def pymaxflow_expansion(
    unary: np.ndarray, edges: np.ndarray, weight: float, max_sweeps: int
) -> np.ndarray:
    """Alpha-expansion with each move cut by PyMaxflow (as the context step was first built;
    ``benchmarks/bench_graph_cut.py`` runs it as the library a user would call)."""
    n, n_labels = unary.shape
    first, second = np.ascontiguousarray(edges[:, 0]), np.ascontiguousarray(edges[:, 1])
    current = unary.argmin(axis=1).astype(np.int64)
    energy = potts_energy(unary, edges, current, weight=weight)
    terminal, forward, backward = np.empty(n), np.empty(first.size), np.empty(first.size)
    for _ in range(max_sweeps):
        changed = False
        for alpha in range(n_labels):
            expansion_capacities(
                unary, first, second, current, alpha, weight, terminal, forward, backward
            )
            graph = maxflow.Graph[float](n, first.size)
            nodes = graph.add_nodes(n)
            graph.add_grid_tedges(nodes, np.maximum(terminal, 0), np.maximum(-terminal, 0))
            graph.add_edges(first, second, forward, backward)
            graph.maxflow()
            proposal = np.where(graph.get_grid_segments(nodes), alpha, current)
            proposed = potts_energy(unary, edges, proposal, weight=weight)
            if proposed < energy - 1e-9:
                current, energy, changed = proposal, proposed, True
        if not changed:
            break
    return current


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(("weight", "max_sweeps"), [(0.5, 1), (4.0, 1), (4.0, 3), (12.0, 2)])
def test_alpha_expansion_gives_the_labels_of_the_pymaxflow_moves(
    seed: int, weight: float, max_sweeps: int
) -> None:
    rng = np.random.default_rng(seed)
    n, n_labels = 3000, 6
    xyz = rng.random((n, 3)) * [20.0, 20.0, 3.0]
    # probabilities with a spatial trend and noise, like a classifier's on a scan
    logits = (
        rng.normal(size=(n, n_labels))
        + 2.5 * np.eye(n_labels)[(xyz[:, 0] // 4).astype(int) % n_labels]
    )
    proba = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    unary, edges = unary_costs(proba), knn_edges(xyz, k=8)
    labels = alpha_expansion(unary, edges, weight=weight, max_sweeps=max_sweeps)
    np.testing.assert_array_equal(labels, pymaxflow_expansion(unary, edges, weight, max_sweeps))
    assert np.any(labels != unary.argmin(axis=1))  # the moves did change labels


def test_expansion_runs_on_several_threads_at_once() -> None:
    # compiled without the GIL, so two scans' graphs are cut at the same time; the results
    # do not depend on what runs beside them
    assert expand_labels.targetoptions.get("nogil") and max_flow.targetoptions.get("nogil")
    rng = np.random.default_rng(7)
    problems = []
    for _ in range(4):
        xyz = rng.random((2000, 3))
        unary = unary_costs(rng.dirichlet(np.ones(5) * 0.5, size=2000))
        problems.append((unary, knn_edges(xyz, k=8)))
    alone = [alpha_expansion(u, e, weight=2.0, max_sweeps=2) for u, e in problems]
    together: list[np.ndarray | None] = [None] * len(problems)

    def run(index: int) -> None:
        unary, edges = problems[index]
        together[index] = alpha_expansion(unary, edges, weight=2.0, max_sweeps=2)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(problems))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for expected, found in zip(alone, together, strict=True):
        np.testing.assert_array_equal(found, expected)


def test_graphs_are_numbered_in_int32_while_they_fit() -> None:
    assert index_type(10, 40).dtype == np.int32
    assert index_type(3_000_000, 12_000_000).dtype == np.int32
    assert index_type(10, 2**30).dtype == np.int64  # 2**31 arcs
    assert index_type(2**31, 10).dtype == np.int64


@settings(max_examples=100, deadline=None)
@given(graphs(), st.integers(0, 3), st.sampled_from([0.5, 4.0]))
def test_move_capacities_written_onto_arcs_are_those_of_the_edges(
    graph: tuple[np.ndarray, ...], alpha: int, weight: float
) -> None:
    from semantic3d.baselines.covariance._context_kernels import expansion_arcs

    first, second, _, _, source, _ = graph
    n = source.size
    rng = np.random.default_rng(n + first.size)
    unary = rng.random((n, 4)) * 3
    current = rng.integers(0, 4, n).astype(np.int64)
    terminal, forward, backward = np.empty(n), np.empty(first.size), np.empty(first.size)
    expansion_capacities(unary, first, second, current, alpha, weight, terminal, forward, backward)
    _, _, _, forward_arc, backward_arc = arc_layout(n, first, second, index_type(n, first.size))
    on_arcs, residual = np.empty(n), np.full(2 * first.size, np.nan)
    expansion_arcs(
        unary, first, second, current, alpha, weight, on_arcs, forward_arc, backward_arc, residual
    )
    np.testing.assert_array_equal(on_arcs, terminal)
    np.testing.assert_array_equal(residual[forward_arc], forward)
    np.testing.assert_array_equal(residual[backward_arc], backward)
