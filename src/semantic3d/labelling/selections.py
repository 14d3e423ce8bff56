"""Selections in a fixed view: keep the working points inside (or outside) a polygon or a mask.

The paper's 2D workflow: a polygon drawn on the screen extrudes through every depth; a
lasso or a brush stroke is rasterised on the page and sent as a bit mask of the screen.
Both apply to every editable working point of the scan, never only to what the screen
shows: a polygon through the octree nodes across its edges (:mod:`.node_split`; the
others are decided whole), a mask by one compiled pass over every point
(:mod:`._op_kernels`, on threads: :func:`.blocks.map_blocks`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.labelling import _op_kernels as kernels
from semantic3d.labelling import geometry
from semantic3d.labelling.delta import Delta, empty_bits
from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.node_split import split_flips_by_nodes
from semantic3d.labelling.session import LabelSession, OperationResult

__all__ = ["split", "split_mask"]


def split(
    session: LabelSession, view_projection: ArrayLike, polygon: ArrayLike, *, keep: str = "inside"
) -> OperationResult:
    """Keep the working points inside (``keep="inside"``) or outside a screen polygon."""
    if keep not in ("inside", "outside"):
        raise OperationError(f"keep: expected 'inside' or 'outside', found {keep!r}")
    matrix = geometry._as_matrix(view_projection)
    vertices = geometry._as_polygon(polygon)
    with session.lock, session._run("split"):
        flip = empty_bits(session.n_points)
        editable = session.editable_layers()
        split_flips_by_nodes(
            session, matrix, vertices, keep_inside=keep == "inside", editable=editable, flip=flip
        )
        operation = {
            "name": "split",
            "keep": keep,
            "view_projection": matrix.reshape(-1).tolist(),
            "polygon": vertices.tolist(),
        }
        return session._commit(operation, Delta.working_only(session.n_points, flip))


def split_mask(
    session: LabelSession,
    view_projection: ArrayLike,
    mask: NDArray[np.uint8],
    *,
    width: int,
    height: int,
    keep: str = "inside",
) -> OperationResult:
    """Keep the working points inside (or outside) a screen mask (a lasso, a brush stroke).

    ``mask`` packs ``width * height`` bits row by row from the top-left pixel (little
    bit order); the view is the camera the mask was drawn in.
    """
    if keep not in ("inside", "outside"):
        raise OperationError(f"keep: expected 'inside' or 'outside', found {keep!r}")
    if not (0 < width <= 8192 and 0 < height <= 8192):
        raise OperationError(f"mask: expected 1..8192 pixels a side, found {width}×{height}")
    bits = np.asarray(mask, np.uint8).reshape(-1)
    if bits.size != (width * height + 7) // 8:
        raise OperationError(
            f"mask: expected {(width * height + 7) // 8} bytes for {width}×{height} "
            f"pixels, found {bits.size}"
        )
    if not bits.any():
        raise OperationError("mask: expected at least one painted pixel, found none")
    matrix = geometry._as_matrix(view_projection)
    with session.lock, session._run("split"):
        flip = empty_bits(session.n_points)
        editable = session.editable_layers()
        session.map_blocks(
            lambda start, xyz: kernels.mask_flips(
                xyz, start, session.origin, session.labels, session.working, editable,
                matrix, bits, width, height, keep == "inside", flip,
            )
        )  # fmt: skip
        operation = {
            "name": "split_mask",
            "keep": keep,
            "view_projection": matrix.reshape(-1).tolist(),
            "width": width,
            "height": height,
            "painted": int(kernels.count_bits(bits)),
        }
        return session._commit(operation, Delta.working_only(session.n_points, flip))
