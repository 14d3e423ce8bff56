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

The result equals the pass over every point (tested), since every decision is the
per-point test's or provably the same. A split of a 60 m square around the scanner of a
simulated 10**7-point scan reads the indices of 6 % of its points and the positions of 4 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.labelling import _split_kernels as kernels
from semantic3d.labelling.blocks import CoordinateReader
from semantic3d.labelling.session import LabelSession

__all__ = ["NodeSplit", "split_flips_by_nodes"]

RUN_ROWS = 4096
"""Points re-read from float64 coordinates are read in runs of at most this many rows."""


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
) -> NodeSplit:
    """Mark in ``flip`` the active points whose side of the polygon is not kept."""
    lod = session.lod
    nodes = [node for node in lod.nodes if node.count]
    bounds = np.array([node.bounds for node in nodes], np.float64).reshape(-1, 6)
    margin = 1e-6 + 1e-9 * float(lod.cube_size)  # points lie in their node's cube
    codes = np.empty(len(nodes), np.int8)
    kernels.classify_boxes(bounds, margin, matrix, vertices, codes)
    kept = kernels.INSIDE if keep_inside else kernels.OUTSIDE
    leaving = kernels.OUTSIDE if keep_inside else kernels.INSIDE
    read = [(node, code) for node, code in zip(nodes, codes, strict=True) if code != kept]
    session.progress.set_total(sum(node.count for node, _ in read))
    labels, working = session.labels, session.working
    unsure: list[NDArray[np.int64]] = []
    done = points_whole = points_across = 0
    for node, code in read:
        session.progress.update(done)
        done += node.count
        if code == leaving:
            kernels.flip_active_at(lod.node_indices(node.id), labels, working, editable, flip)
            points_whole += node.count
            continue
        for positions, index in lod.iter_positions(node.id):
            if not kernels.any_active_at(index, labels, working, editable):
                continue
            found = np.empty(len(index), np.int64)
            n_found = kernels.split_flips_near(
                positions, index, labels, working, editable, matrix, vertices, keep_inside,
                flip, found, 0,
            )  # fmt: skip
            points_across += len(index)
            if n_found:
                unsure.append(found[:n_found])
    retested = np.sort(np.concatenate(unsure)) if unsure else np.empty(0, np.int64)
    _retest(session, retested, matrix, vertices, keep_inside, flip)
    session.progress.update(done)
    n_across = int((codes == kernels.ACROSS).sum())
    return NodeSplit(
        nodes_skipped=len(nodes) - len(read),
        nodes_whole=len(read) - n_across,
        nodes_across=n_across,
        points_whole=points_whole,
        points_across=points_across,
        points_retested=len(retested),
    )


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
    with CoordinateReader(session) as reader:
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
