"""A polygon split that reads only the octree nodes across the polygon's edges.

A split keeps the working points on one side of a polygon drawn in a view. Instead of
testing every point of the scan (reading its float64 coordinates, 24 bytes a point), the
octree's node boxes are projected first (:mod:`._split_kernels`):

- a node wholly on the kept side changes nothing and is not read;
- a node wholly on the other side loses its active points: only its scan indices are read
  (4 bytes a point);
- a node across an edge is tested point by point from its float32 positions (12 bytes a
  point); the few points too close to an edge for the float32 copy to decide are tested
  again from their float64 coordinates, read in short runs.

The nodes read are cut into tasks of about :data:`TASK_POINTS` points, run on numba's
number of threads (:func:`.blocks.block_threads`): each thread reads its nodes and runs
the compiled kernels without the GIL, marking a bit mask of its own (the first thread's
is the result itself; the others are OR-ed into it at the end), and the points to test
again are gathered in task order, so the mask does not depend on the threads.

The result equals the pass over every point (tested), since every decision is the
per-point test's or provably the same. A split of a 60 m square around the scanner of a
simulated 10**7-point scan reads the indices of 6 % of its points and the positions of 4 %.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.labelling import _split_kernels as kernels
from semantic3d.labelling import blocks
from semantic3d.labelling.delta import empty_bits
from semantic3d.labelling.session import LabelSession

__all__ = ["NodeSplit", "split_flips_by_nodes"]

RUN_ROWS = 4096
"""Points re-read from float64 coordinates are read in runs of at most this many rows."""
TASK_POINTS = 1 << 18
"""Points one task of a split reads at most (runs of consecutive nodes decided alike)."""


@dataclass(frozen=True, slots=True)
class NodeSplit:
    """What a split over the nodes read: nodes decided whole, points read, points re-read."""

    nodes_skipped: int
    nodes_whole: int
    nodes_across: int
    points_whole: int
    points_across: int
    points_retested: int


def split_flips_by_nodes(
    session: LabelSession,
    matrix: NDArray[np.float64],
    vertices: NDArray[np.float64],
    *,
    keep_inside: bool,
    editable: NDArray[np.bool_],
    flip: NDArray[np.uint8],
    threads: int | None = None,
) -> NodeSplit:
    """Mark in ``flip`` the active points whose side of the polygon is not kept.

    Runs on ``threads`` threads (default: :func:`.blocks.block_threads`); the mask is the
    same on any number of them.
    """
    lod = session.lod
    nodes = np.flatnonzero(lod.node_counts > 0)
    margin = 1e-6 + 1e-9 * float(lod.cube_size)  # points lie in their node's cube
    codes = np.empty(len(nodes), np.int8)
    kernels.classify_boxes(lod.node_bounds[nodes], margin, matrix, vertices, codes)
    kept = kernels.INSIDE if keep_inside else kernels.OUTSIDE
    leaving = kernels.OUTSIDE if keep_inside else kernels.INSIDE
    read = nodes[codes != kept]
    session.progress.set_total(int(lod.node_counts[read].sum()))
    labels, working = session.labels, session.working
    tasks = _tasks(
        lod.node_starts[read].tolist(),
        lod.node_counts[read].tolist(),
        (codes[codes != kept] == leaving).tolist(),
    )
    masks: list[NDArray[np.uint8]] = []
    masks_lock = threading.Lock()
    local = threading.local()
    stopping = threading.Event()

    def mask_of_this_thread() -> NDArray[np.uint8]:
        mask = getattr(local, "mask", None)
        if mask is None:
            with masks_lock:
                mask = flip if not masks else empty_bits(len(labels))
                masks.append(mask)
            local.mask = mask
        return mask

    passed = [0]  # points of the nodes done, for the progress (any thread)
    passed_lock = threading.Lock()

    def advance(points: int) -> None:
        """Report the progress; raises when the operation was cancelled."""
        with passed_lock:
            passed[0] += points
            session.progress.update(passed[0])

    def run(task: list[_Run]) -> _TaskResult:
        if stopping.is_set():  # cancelled: the split is dropped
            return _TaskResult([], 0, 0)
        mask = mask_of_this_thread()
        unsure: list[NDArray[np.int64]] = []
        points_whole = points_across = 0
        for piece in task:
            advance(0)
            index = lod.read_indices(piece.start, piece.count)
            if piece.whole:
                kernels.flip_active_at(index, labels, working, editable, mask)
                points_whole += piece.count
            elif kernels.any_active_at(index, labels, working, editable):
                positions = lod.read_positions(piece.start, piece.count)
                found = np.empty(piece.count, np.int64)
                n_found = kernels.split_flips_near(
                    positions, index, labels, working, editable, matrix, vertices,
                    keep_inside, mask, found, 0,
                )  # fmt: skip
                points_across += piece.count
                if n_found:
                    unsure.append(found[:n_found].copy())
            advance(piece.count)
        return _TaskResult(unsure, points_whole, points_across)

    results: list[_TaskResult] = []
    count = max(1, min(threads or blocks.block_threads(), len(tasks)))
    session.progress.update(0)
    with ThreadPoolExecutor(count, thread_name_prefix="labelling-split") as pool:
        futures: list[Future[_TaskResult]] = [pool.submit(run, task) for task in tasks]
        try:
            results.extend(future.result() for future in futures)
        except BaseException:
            stopping.set()
            for future in futures:
                future.cancel()
            raise
    for mask in masks[1:]:
        kernels.or_into(flip, mask)
    unsure = [found for result in results for found in result.unsure]
    retested = np.sort(np.concatenate(unsure)) if unsure else np.empty(0, np.int64)
    _retest(session, retested, matrix, vertices, keep_inside, flip)
    session.progress.update(passed[0])
    n_across = int((codes == kernels.ACROSS).sum())
    return NodeSplit(
        nodes_skipped=len(nodes) - len(read),
        nodes_whole=len(read) - n_across,
        nodes_across=n_across,
        points_whole=sum(result.points_whole for result in results),
        points_across=sum(result.points_across for result in results),
        points_retested=len(retested),
    )


@dataclass(frozen=True, slots=True)
class _TaskResult:
    unsure: list[NDArray[np.int64]]
    points_whole: int
    points_across: int


@dataclass(frozen=True, slots=True)
class _Run:
    """Points ``start .. start + count`` in node order (consecutive nodes, read at once),
    wholly on the side not kept (``whole``) or across an edge."""

    start: int
    count: int
    whole: bool


def _tasks(starts: list[int], counts: list[int], whole: list[bool]) -> list[list[_Run]]:
    """Runs of consecutive nodes decided alike (their points ``starts[k] ..
    starts[k] + counts[k]`` in node order; ``whole``: wholly on the side not kept), in node
    order, cut into pieces read at once (at most a block of :data:`.blocks.BLOCK_POINTS`
    points: 24 bytes each held in memory, as a block of coordinates), in tasks of at most
    :data:`TASK_POINTS` points."""
    runs: list[_Run] = []
    for start, count, all_leave in zip(starts, counts, whole, strict=True):
        last = runs[-1] if runs else None
        if last is not None and last.whole == all_leave and last.start + last.count == start:
            runs[-1] = _Run(last.start, last.count + count, all_leave)
        else:
            runs.append(_Run(start, count, all_leave))
    tasks: list[list[_Run]] = []
    held = TASK_POINTS
    piece = max(8, min(TASK_POINTS, blocks.BLOCK_POINTS))  # 24 bytes a point in memory
    for run in runs:
        for start in range(run.start, run.start + run.count, piece):
            count = min(piece, run.start + run.count - start)
            if held + count > TASK_POINTS:
                tasks.append([])
                held = 0
            tasks[-1].append(_Run(start, count, run.whole))
            held += count
    return tasks


def _retest(
    session: LabelSession,
    points: NDArray[np.int64],
    matrix: NDArray[np.float64],
    vertices: NDArray[np.float64],
    keep_inside: bool,
    flip: NDArray[np.uint8],
) -> None:
    """The float64 test of ``points`` (sorted indices), read in runs of ``RUN_ROWS`` rows."""
    if not len(points):
        return
    rows = np.empty((RUN_ROWS, 3), np.float64)
    with blocks.CoordinateReader(session) as reader:
        first = 0
        while first < len(points):
            start = int(points[first])
            end = int(np.searchsorted(points, start + RUN_ROWS, side="left"))
            span = int(points[end - 1]) - start + 1
            reader.read(start, rows[:span])
            kernels.split_flips_rows(
                rows, start, points[first:end], session.origin, matrix, vertices, keep_inside, flip
            )
            first = end
