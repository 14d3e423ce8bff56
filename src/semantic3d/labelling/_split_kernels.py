"""Compiled passes of a polygon split over the octree nodes (numba).

Hand-written, like :mod:`._op_kernels`: a split over every point reads all the scan's
float64 coordinates (2.4 GB at 10**8 points). Most octree nodes lie wholly inside or
wholly outside the polygon on the screen; only the points of the nodes across its edges
need a test. Every decision here equals the per-point test of the pass over every point
(:func:`._op_kernels.split_flips`, :func:`._op_kernels.in_split_polygon`):

- a node box is decided whole only when no polygon edge comes near its projected corners'
  rectangle (widened by far more than rounding) and all its corners are on one side of the
  camera plane;
- a point of a node across an edge is tested from its float32 re-centred position (the
  level of detail's copy, within 2**-24 of the float64 one in each coordinate) when that
  error, carried through the projection, cannot move it across an edge; otherwise its
  index is returned and it is tested again from the float64 coordinates.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from semantic3d.labelling._op_kernels import in_polygon, in_split_polygon, polygon_box

OUTSIDE = 0
INSIDE = 1
ACROSS = 2

# Bounds of the float32 copy's error (2**-24 relative, taken 4x) and of float64 rounding
# in a sum of a few products (2**-53 per operation, taken 32x).
_COPY_ERROR = 2.0**-22
_ROUNDING = 2.0**-48


@nb.njit(cache=True, nogil=True, inline="always")
def _meets_edges(low_u, high_u, low_v, high_v, vertices):  # type: ignore[no-untyped-def]
    """Whether a polygon edge may meet the rectangle (``True`` when unsure)."""
    m = vertices.shape[0]
    x0, y0 = vertices[m - 1, 0], vertices[m - 1, 1]
    for k in range(m):
        x1, y1 = vertices[k, 0], vertices[k, 1]
        if not (
            max(x0, x1) < low_u
            or min(x0, x1) > high_u
            or max(y0, y1) < low_v
            or min(y0, y1) > high_v
        ):
            dx, dy = x1 - x0, y1 - y0
            s1 = dx * (low_v - y0) - dy * (low_u - x0)
            s2 = dx * (low_v - y0) - dy * (high_u - x0)
            s3 = dx * (high_v - y0) - dy * (low_u - x0)
            s4 = dx * (high_v - y0) - dy * (high_u - x0)
            if not (
                (s1 > 0 and s2 > 0 and s3 > 0 and s4 > 0)
                or (s1 < 0 and s2 < 0 and s3 < 0 and s4 < 0)
            ):
                return True
        x0, y0 = x1, y1
    return False


@nb.njit(cache=True, nogil=True)
def classify_boxes(bounds, margin, matrix, vertices, codes):  # type: ignore[no-untyped-def]
    """``codes[b]``: OUTSIDE / INSIDE when every point of box ``b`` is outside / inside the
    polygon by the split's test, ACROSS otherwise.

    ``bounds`` (n, 6) re-centred (x0, y0, z0, x1, y1, z1), widened by ``margin`` here.
    """
    scale = 1.0
    for k in range(vertices.shape[0]):
        scale = max(scale, abs(vertices[k, 0]), abs(vertices[k, 1]))
    for b in range(bounds.shape[0]):
        low_w, high_w, size = np.inf, -np.inf, 0.0
        low_u, high_u, low_v, high_v = np.inf, -np.inf, np.inf, -np.inf
        for corner in range(8):
            x = bounds[b, 3] + margin if corner & 1 else bounds[b, 0] - margin
            y = bounds[b, 4] + margin if corner & 2 else bounds[b, 1] - margin
            z = bounds[b, 5] + margin if corner & 4 else bounds[b, 2] - margin
            size = max(size, abs(x), abs(y), abs(z))
            w = matrix[3, 0] * x + matrix[3, 1] * y + matrix[3, 2] * z + matrix[3, 3]
            low_w, high_w = min(low_w, w), max(high_w, w)
            if w > 0:
                u = (matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z + matrix[0, 3]) / w
                v = (matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z + matrix[1, 3]) / w
                low_u, high_u = min(low_u, u), max(high_u, u)
                low_v, high_v = min(low_v, v), max(high_v, v)
        slack = 1e-9 * (
            abs(matrix[3, 0]) * size + abs(matrix[3, 1]) * size + abs(matrix[3, 2]) * size
            + abs(matrix[3, 3])
        )  # fmt: skip
        if high_w + slack <= 1e-12:  # wholly behind the camera: nothing is inside
            codes[b] = OUTSIDE
            continue
        if low_w - slack <= 1e-12:
            codes[b] = ACROSS
            continue
        # In front: the points project into the corners' rectangle (a box's projection is
        # the hull of its corners'); widen it by far more than rounding.
        widen = 1e-9 * max(scale, abs(low_u), abs(high_u), abs(low_v), abs(high_v))
        low_u, high_u, low_v, high_v = low_u - widen, high_u + widen, low_v - widen, high_v + widen
        if _meets_edges(low_u, high_u, low_v, high_v, vertices):
            codes[b] = ACROSS
        elif in_polygon(0.5 * (low_u + high_u), 0.5 * (low_v + high_v), vertices):
            codes[b] = INSIDE
        else:
            codes[b] = OUTSIDE


@nb.njit(cache=True, nogil=True)
def flip_active_at(index, labels, working, editable, flip):  # type: ignore[no-untyped-def]
    """Mark every active point among ``index`` (a node wholly on the side not kept)."""
    for r in range(index.shape[0]):
        i = index[r]
        if working[i] and editable[labels[i]]:
            flip[i >> 3] |= np.uint8(1 << (i & 7))


@nb.njit(cache=True, nogil=True)
def any_active_at(index, labels, working, editable):  # type: ignore[no-untyped-def]
    for r in range(index.shape[0]):  # a loop: numba compiles it, not any()
        i = index[r]
        if working[i] and editable[labels[i]]:
            return True
    return False


@nb.njit(cache=True, nogil=True)
def split_flips_near(  # type: ignore[no-untyped-def]
    positions, index, labels, working, editable, matrix, vertices, keep_inside, flip, unsure,
    n_unsure,
):  # fmt: skip
    """Mark the active points of a node across the polygon from their float32 positions.

    Points whose float64 test could answer otherwise are not marked: their indices go to
    ``unsure[n_unsure:]``. Returns the new ``n_unsure``.
    """
    scale = 1.0
    for k in range(vertices.shape[0]):
        scale = max(scale, abs(vertices[k, 0]), abs(vertices[k, 1]))
    for r in range(positions.shape[0]):
        i = index[r]
        if not (working[i] and editable[labels[i]]):
            continue
        x, y, z = (
            np.float64(positions[r, 0]),
            np.float64(positions[r, 1]),
            np.float64(positions[r, 2]),
        )
        ax, ay, az = abs(x), abs(y), abs(z)
        w = matrix[3, 0] * x + matrix[3, 1] * y + matrix[3, 2] * z + matrix[3, 3]
        reach_w = abs(matrix[3, 0]) * ax + abs(matrix[3, 1]) * ay + abs(matrix[3, 2]) * az
        error_w = _COPY_ERROR * reach_w + _ROUNDING * (reach_w + abs(matrix[3, 3]))
        inside = False
        sure = True
        if w - error_w > 1e-12:
            nu = matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z + matrix[0, 3]
            nv = matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z + matrix[1, 3]
            reach_u = abs(matrix[0, 0]) * ax + abs(matrix[0, 1]) * ay + abs(matrix[0, 2]) * az
            reach_v = abs(matrix[1, 0]) * ax + abs(matrix[1, 1]) * ay + abs(matrix[1, 2]) * az
            error_u = _COPY_ERROR * reach_u + _ROUNDING * (reach_u + abs(matrix[0, 3]))
            error_v = _COPY_ERROR * reach_v + _ROUNDING * (reach_v + abs(matrix[1, 3]))
            u, v = nu / w, nv / w
            # |u(float64) - u(float32)| <= (error_u + |u| error_w) / (w - error_w), plus the
            # rounding of the division; twice that keeps the float64 point off the edges.
            du = 2.0 * ((error_u + abs(u) * error_w) / (w - error_w) + _ROUNDING * (abs(u) + scale))
            dv = 2.0 * ((error_v + abs(v) * error_w) / (w - error_w) + _ROUNDING * (abs(v) + scale))
            if _meets_edges(u - du, u + du, v - dv, v + dv, vertices):
                sure = False
            else:
                inside = in_polygon(u, v, vertices)
        elif w + error_w > 1e-12:
            sure = False
        if not sure:
            unsure[n_unsure] = i
            n_unsure += 1
        elif inside != keep_inside:
            flip[i >> 3] |= np.uint8(1 << (i & 7))
    return n_unsure


@nb.njit(cache=True, nogil=True)
def split_flips_rows(  # type: ignore[no-untyped-def]
    rows, first, points, origin, matrix, vertices, keep_inside, flip
):
    """The split's float64 test of ``points`` (indices), whose rows are ``rows[i - first]``."""
    low_u, high_u, low_v, high_v = polygon_box(vertices)
    for r in range(points.shape[0]):
        i = points[r]
        x = rows[i - first, 0] - origin[0]
        y = rows[i - first, 1] - origin[1]
        z = rows[i - first, 2] - origin[2]
        inside = in_split_polygon(x, y, z, matrix, vertices, low_u, high_u, low_v, high_v)
        if inside != keep_inside:
            flip[i >> 3] |= np.uint8(1 << (i & 7))


@nb.njit(cache=True, nogil=True)
def or_into(flip, mask):  # type: ignore[no-untyped-def]
    """``flip |= mask`` (bit masks of the same length)."""
    for k in range(flip.shape[0]):
        if mask[k]:
            flip[k] |= mask[k]
