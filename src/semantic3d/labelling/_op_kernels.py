"""Compiled passes of the labelling operations (numba).

Hand-written: at 10**8 points the numpy versions (``working & editable`` masks, ``!=``
comparisons, ``flatnonzero`` to int64 indices) allocated up to 1 GB per operation and took
seconds. Each pass here is one loop writing into a packed bit mask (one bit per point:
12.5 MB at 10**8) and, for label changes, the old label of each changed point.

``editable`` is a lookup table over the 9 label values (a layer neither hidden nor locked).
Bit ``i`` of a mask is ``mask[i >> 3] >> (i & 7) & 1`` (little bit order, as
``np.packbits(..., bitorder="little")``).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def count_bits(mask):  # type: ignore[no-untyped-def]
    """The number of bits set in a mask (8 bytes at a time: 12.5 MB in under a millisecond)."""
    n_words = mask.shape[0] // 8
    words = mask[: n_words * 8].view(np.uint64)
    m1 = np.uint64(0x5555555555555555)
    m2 = np.uint64(0x3333333333333333)
    m4 = np.uint64(0x0F0F0F0F0F0F0F0F)
    ones = np.uint64(0x0101010101010101)
    total = 0
    for k in range(n_words):
        x = words[k]
        x = x - ((x >> np.uint64(1)) & m1)
        x = (x & m2) + ((x >> np.uint64(2)) & m2)
        x = (x + (x >> np.uint64(4))) & m4
        total += int((x * ones) >> np.uint64(56))
    for b in range(n_words * 8, mask.shape[0]):
        v = mask[b]
        while v:
            v &= v - 1
            total += 1
    return total


@nb.njit(cache=True, nogil=True)
def apply_delta(labels, working, changed, values, single, flip, forward):  # type: ignore[no-untyped-def]
    """Apply (``forward``) or revert a delta in place.

    ``changed`` marks the points whose label changes; forward they take ``values[j]`` (the
    ``j``-th changed point) or ``single`` when ``single >= 0``; backward ``values[j]`` are
    their old labels. ``flip`` marks the points that enter or leave the working set.
    """
    j = 0
    for b in range(changed.shape[0]):
        v = changed[b]
        if v == 0:
            continue
        for bit in range(8):
            if (v >> bit) & 1:
                i = (b << 3) | bit
                labels[i] = values[j] if single < 0 else single
                j += 1
    n = working.shape[0]
    for b in range(flip.shape[0]):
        v = flip[b]
        if v == 0:
            continue
        base = b << 3
        if base + 8 <= n:  # all 8 points, without a branch per bit
            for bit in range(8):
                working[base + bit] = working[base + bit] ^ (((v >> bit) & 1) != 0)
            continue
        for bit in range(n - base):
            if (v >> bit) & 1:
                working[base + bit] = not working[base + bit]


@nb.njit(cache=True, nogil=True)
def assign_marks(labels, working, editable, value, changed):  # type: ignore[no-untyped-def]
    """Mark the editable working points whose label is not ``value``; return their count."""
    n = 0
    for i in range(labels.shape[0]):
        label = labels[i]
        if working[i] and editable[label] and label != value:
            changed[i >> 3] |= np.uint8(1 << (i & 7))
            n += 1
    return n


@nb.njit(cache=True, nogil=True)
def layer_marks(labels, source, changed):  # type: ignore[no-untyped-def]
    """Mark the points of layer ``source``; return their count."""
    n = 0
    for i in range(labels.shape[0]):
        if labels[i] == source:
            changed[i >> 3] |= np.uint8(1 << (i & 7))
            n += 1
    return n


@nb.njit(cache=True, nogil=True)
def gather_marked(labels, changed, out):  # type: ignore[no-untyped-def]
    """The labels of the marked points, in index order."""
    j = 0
    for b in range(changed.shape[0]):
        v = changed[b]
        if v == 0:
            continue
        for bit in range(8):
            if (v >> bit) & 1:
                out[j] = labels[(b << 3) | bit]
                j += 1


@nb.njit(cache=True, nogil=True)
def reset_flips(labels, working, editable, unlabelled_only, flip):  # type: ignore[no-untyped-def]
    """Mark the points whose working flag differs from the reset's (editable [& label 0])."""
    n = 0
    for i in range(labels.shape[0]):
        label = labels[i]
        wanted = editable[label] and (label == 0 or not unlabelled_only)
        if wanted != working[i]:
            flip[i >> 3] |= np.uint8(1 << (i & 7))
            n += 1
    return n


@nb.njit(cache=True, nogil=True)
def any_active(labels, working, editable, start, stop):  # type: ignore[no-untyped-def]
    # A loop, not any(generator): numba compiles this one.
    for i in range(start, stop):  # noqa: SIM110
        if working[i] and editable[labels[i]]:
            return True
    return False


@nb.njit(cache=True, nogil=True, inline="always")
def in_polygon(u, v, vertices):  # type: ignore[no-untyped-def]
    """Even-odd rule (as :func:`.geometry.points_in_polygon`): is ``(u, v)`` inside."""
    m = vertices.shape[0]
    inside = False
    x0, y0 = vertices[m - 1, 0], vertices[m - 1, 1]
    for k in range(m):
        x1, y1 = vertices[k, 0], vertices[k, 1]
        if ((y0 > v) != (y1 > v)) and u < x0 + (v - y0) / (y1 - y0) * (x1 - x0):
            inside = not inside
        x0, y0 = x1, y1
    return inside


@nb.njit(cache=True, nogil=True, inline="always")
def in_split_polygon(x, y, z, matrix, vertices, low_u, high_u, low_v, high_v):  # type: ignore[no-untyped-def]
    """The split's test of one re-centred point: in front of the camera, inside the polygon.

    A point outside the polygon's bounding box (``low_u``..``high_v``, widened by far more
    than rounding) is outside without testing the edges; a view with ``w == 1`` (the fixed
    2D views) needs no division (``u / 1.0 == u``). Both give the full test's answer.
    """
    w = matrix[3, 0] * x + matrix[3, 1] * y + matrix[3, 2] * z + matrix[3, 3]
    if not w > 1e-12:
        return False
    u = matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z + matrix[0, 3]
    v = matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z + matrix[1, 3]
    if w != 1.0:
        u /= w
        v /= w
    if not (low_u <= u <= high_u and low_v <= v <= high_v):
        return False
    return in_polygon(u, v, vertices)


@nb.njit(cache=True, nogil=True)
def polygon_box(vertices):  # type: ignore[no-untyped-def]
    """The polygon's bounding box, widened by 1e-9 of its size (far more than rounding)."""
    low_u, high_u = vertices[:, 0].min(), vertices[:, 0].max()
    low_v, high_v = vertices[:, 1].min(), vertices[:, 1].max()
    margin = 1e-9 * (1.0 + max(abs(low_u), abs(high_u), abs(low_v), abs(high_v)))
    return low_u - margin, high_u + margin, low_v - margin, high_v + margin


@nb.njit(cache=True, nogil=True)
def split_flips(  # type: ignore[no-untyped-def]
    xyz, start, origin, labels, working, editable, matrix, vertices, keep_inside, flip
):
    """Mark the active points of a block whose side of the polygon is not kept.

    The test of :func:`in_split_polygon` written out in the loop (the same operations, so
    the same answers): compiled this way the pass takes 2/3 of the time.
    """
    m = vertices.shape[0]
    low_u, high_u = vertices[:, 0].min(), vertices[:, 0].max()
    low_v, high_v = vertices[:, 1].min(), vertices[:, 1].max()
    margin = 1e-9 * (1.0 + max(abs(low_u), abs(high_u), abs(low_v), abs(high_v)))
    low_u, high_u, low_v, high_v = low_u - margin, high_u + margin, low_v - margin, high_v + margin
    n = 0
    for r in range(xyz.shape[0]):
        i = start + r
        if not (working[i] and editable[labels[i]]):
            continue
        x = xyz[r, 0] - origin[0]
        y = xyz[r, 1] - origin[1]
        z = xyz[r, 2] - origin[2]
        w = matrix[3, 0] * x + matrix[3, 1] * y + matrix[3, 2] * z + matrix[3, 3]
        inside = False
        if w > 1e-12:
            u = matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z + matrix[0, 3]
            v = matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z + matrix[1, 3]
            if w != 1.0:
                u /= w
                v /= w
            if low_u <= u <= high_u and low_v <= v <= high_v:
                x0, y0 = vertices[m - 1, 0], vertices[m - 1, 1]
                for k in range(m):
                    x1, y1 = vertices[k, 0], vertices[k, 1]
                    if ((y0 > v) != (y1 > v)) and u < x0 + (v - y0) / (y1 - y0) * (x1 - x0):
                        inside = not inside
                    x0, y0 = x1, y1
        if inside != keep_inside:
            flip[i >> 3] |= np.uint8(1 << (i & 7))
            n += 1
    return n


# Models: kind 0 plane (point, normal), 1 line (point, direction), 2 cylinder (point, axis,
# radius), 3 sphere (centre, radius). ``model`` = [px, py, pz, vx, vy, vz, radius].
# Regions: kind 0 none, 1 sphere (cx, cy, cz, r), 2 box (x0, y0, z0, x1, y1, z1).


@nb.njit(cache=True, nogil=True, inline="always")
def _distance(kind, model, x, y, z):  # type: ignore[no-untyped-def]
    dx, dy, dz = x - model[0], y - model[1], z - model[2]
    if kind == 3:
        return abs(np.sqrt(dx * dx + dy * dy + dz * dz) - model[6])
    along = dx * model[3] + dy * model[4] + dz * model[5]
    if kind == 0:
        return abs(along)
    radial = np.sqrt(max(dx * dx + dy * dy + dz * dz - along * along, 0.0))
    if kind == 1:
        return radial
    return abs(radial - model[6])


@nb.njit(cache=True, nogil=True, inline="always")
def _in_region(region_kind, region, x, y, z):  # type: ignore[no-untyped-def]
    if region_kind == 1:
        dx, dy, dz = x - region[0], y - region[1], z - region[2]
        return dx * dx + dy * dy + dz * dz <= region[3] * region[3]
    if region_kind == 2:
        return (
            region[0] <= x <= region[3]
            and region[1] <= y <= region[4]
            and region[2] <= z <= region[5]
        )
    return True


@nb.njit(cache=True, nogil=True)
def fit_flips(  # type: ignore[no-untyped-def]
    xyz, start, origin, labels, working, editable, kind, model, tolerance, region_kind, region, flip
):
    """Mark the active points of a block that are not inliers of the model in the region."""
    n = 0
    for r in range(xyz.shape[0]):
        i = start + r
        if not (working[i] and editable[labels[i]]):
            continue
        x = xyz[r, 0] - origin[0]
        y = xyz[r, 1] - origin[1]
        z = xyz[r, 2] - origin[2]
        keep = _in_region(region_kind, region, x, y, z) and (
            _distance(kind, model, x, y, z) <= tolerance
        )
        if not keep:
            flip[i >> 3] |= np.uint8(1 << (i & 7))
            n += 1
    return n


@nb.njit(cache=True, nogil=True, inline="always")
def _uniform(index):  # type: ignore[no-untyped-def]
    z = np.uint64(index) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) / 9007199254740992.0


@nb.njit(cache=True, nogil=True)
def inlier_sample(  # type: ignore[no-untyped-def]
    xyz, start, origin, labels, working, editable, kind, model, tolerance, region_kind, region,
    out, filled, seen,
):  # fmt: skip
    """Count the block's inliers and keep a uniform sample of them in ``out`` (k, 3).

    Reservoir sampling (Algorithm R) with a hash of each point's index as its random
    draw, so the sample does not depend on blocks. Returns the updated (filled, seen,
    sum of squared distances of this block's inliers).
    """
    k = out.shape[0]
    squares = 0.0
    for r in range(xyz.shape[0]):
        i = start + r
        if not (working[i] and editable[labels[i]]):
            continue
        x = xyz[r, 0] - origin[0]
        y = xyz[r, 1] - origin[1]
        z = xyz[r, 2] - origin[2]
        if not _in_region(region_kind, region, x, y, z):
            continue
        d = _distance(kind, model, x, y, z)
        if d > tolerance:
            continue
        squares += d * d
        if filled < k:
            out[filled, 0], out[filled, 1], out[filled, 2] = x, y, z
            filled += 1
        else:
            j = int(_uniform(i) * (seen + 1))
            if j < k:
                out[j, 0], out[j, 1], out[j, 2] = x, y, z
        seen += 1
    return filled, seen, squares


@nb.njit(cache=True, nogil=True)
def region_candidates(  # type: ignore[no-untyped-def]
    xyz, start, origin, labels, working, editable, region_kind, region, out, filled, seen
):
    """A uniform sample (reservoir, as :func:`inlier_sample`) of the active points in the region."""
    k = out.shape[0]
    for r in range(xyz.shape[0]):
        i = start + r
        if not (working[i] and editable[labels[i]]):
            continue
        x = xyz[r, 0] - origin[0]
        y = xyz[r, 1] - origin[1]
        z = xyz[r, 2] - origin[2]
        if not _in_region(region_kind, region, x, y, z):
            continue
        if filled < k:
            out[filled, 0], out[filled, 1], out[filled, 2] = x, y, z
            filled += 1
        else:
            j = int(_uniform(i) * (seen + 1))
            if j < k:
                out[j, 0], out[j, 1], out[j, 2] = x, y, z
        seen += 1
    return filled, seen


@nb.njit(cache=True, nogil=True)
def confusion(  # type: ignore[no-untyped-def]
    labels, prediction, selected, start, stop, matrix
):
    """``matrix[label, prediction]`` (10 × 10; prediction 255 "none" counts in column 9)."""
    for i in range(start, stop):
        if selected[i]:
            p = prediction[i]
            matrix[labels[i], 9 if p > 8 else p] += 1


@nb.njit(cache=True, nogil=True)
def view_confusion(  # type: ignore[no-untyped-def]
    xyz, start, origin, labels, prediction, matrix4, shown, out
):
    """Confusion of the points of a block inside the view frustum whose layer is shown."""
    for r in range(xyz.shape[0]):
        i = start + r
        label = labels[i]
        if not shown[label]:
            continue
        x = xyz[r, 0] - origin[0]
        y = xyz[r, 1] - origin[1]
        z = xyz[r, 2] - origin[2]
        w = matrix4[3, 0] * x + matrix4[3, 1] * y + matrix4[3, 2] * z + matrix4[3, 3]
        if w <= 1e-12:
            continue
        u = (matrix4[0, 0] * x + matrix4[0, 1] * y + matrix4[0, 2] * z + matrix4[0, 3]) / w
        v = (matrix4[1, 0] * x + matrix4[1, 1] * y + matrix4[1, 2] * z + matrix4[1, 3]) / w
        d = (matrix4[2, 0] * x + matrix4[2, 1] * y + matrix4[2, 2] * z + matrix4[2, 3]) / w
        if -1.0 <= u <= 1.0 and -1.0 <= v <= 1.0 and -1.0 <= d <= 1.0:
            p = prediction[i]
            out[label, 9 if p > 8 else p] += 1


@nb.njit(cache=True, nogil=True)
def layer_counts(labels, counts):  # type: ignore[no-untyped-def]
    """Add the number of points of each label value (``np.bincount`` casts to int64 first)."""
    for i in range(labels.shape[0]):
        counts[labels[i]] += 1


@nb.njit(cache=True, nogil=True)
def masked_layer_counts(labels, mask, counts):  # type: ignore[no-untyped-def]
    for i in range(labels.shape[0]):
        if mask[i]:
            counts[labels[i]] += 1


@nb.njit(cache=True, nogil=True)
def count_active(labels, working, editable):  # type: ignore[no-untyped-def]
    """``(editable points, editable working points)``."""
    n_editable = 0
    n_active = 0
    for i in range(labels.shape[0]):
        if editable[labels[i]]:
            n_editable += 1
            if working[i]:
                n_active += 1
    return n_editable, n_active


@nb.njit(cache=True, nogil=True)
def mask_flips(  # type: ignore[no-untyped-def]
    xyz, start, origin, labels, working, editable, matrix, mask, width, height, keep_inside, flip
):
    """Mark the active points of a block whose side of a screen mask is not kept.

    ``mask`` holds ``width * height`` bits, row by row from the top-left pixel; a point is
    inside when it is in front of the camera and the pixel it projects to is set.
    """
    n = 0
    for r in range(xyz.shape[0]):
        i = start + r
        if not (working[i] and editable[labels[i]]):
            continue
        x = xyz[r, 0] - origin[0]
        y = xyz[r, 1] - origin[1]
        z = xyz[r, 2] - origin[2]
        w = matrix[3, 0] * x + matrix[3, 1] * y + matrix[3, 2] * z + matrix[3, 3]
        inside = False
        if w > 1e-12:
            u = matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z + matrix[0, 3]
            v = matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z + matrix[1, 3]
            if w != 1.0:  # the fixed 2D views: no division (u / 1.0 == u)
                u /= w
                v /= w
            px = int(np.floor((u + 1.0) * 0.5 * width))
            py = int(np.floor((1.0 - v) * 0.5 * height))
            if 0 <= px < width and 0 <= py < height:
                bit = py * width + px
                inside = (mask[bit >> 3] >> (bit & 7)) & 1 == 1
        if inside != keep_inside:
            flip[i >> 3] |= np.uint8(1 << (i & 7))
            n += 1
    return n


# Passes over the points of octree nodes (``xyz`` re-centred, ``index`` their scan positions):
# a fit bounded by a region reads only the nodes that meet it.


@nb.njit(cache=True, nogil=True)
def region_candidates_at(  # type: ignore[no-untyped-def]
    xyz, index, labels, working, editable, region_kind, region, out, filled, seen
):
    """:func:`region_candidates` over node points."""
    k = out.shape[0]
    for r in range(xyz.shape[0]):
        i = index[r]
        if not (working[i] and editable[labels[i]]):
            continue
        x, y, z = xyz[r, 0], xyz[r, 1], xyz[r, 2]
        if not _in_region(region_kind, region, x, y, z):
            continue
        if filled < k:
            out[filled, 0], out[filled, 1], out[filled, 2] = x, y, z
            filled += 1
        else:
            j = int(_uniform(i) * (seen + 1))
            if j < k:
                out[j, 0], out[j, 1], out[j, 2] = x, y, z
        seen += 1
    return filled, seen


@nb.njit(cache=True, nogil=True)
def inlier_sample_at(  # type: ignore[no-untyped-def]
    xyz, index, labels, working, editable, kind, model, tolerance, region_kind, region,
    out, filled, seen,
):  # fmt: skip
    """:func:`inlier_sample` over node points."""
    k = out.shape[0]
    squares = 0.0
    for r in range(xyz.shape[0]):
        i = index[r]
        if not (working[i] and editable[labels[i]]):
            continue
        x, y, z = xyz[r, 0], xyz[r, 1], xyz[r, 2]
        if not _in_region(region_kind, region, x, y, z):
            continue
        d = _distance(kind, model, x, y, z)
        if d > tolerance:
            continue
        squares += d * d
        if filled < k:
            out[filled, 0], out[filled, 1], out[filled, 2] = x, y, z
            filled += 1
        else:
            j = int(_uniform(i) * (seen + 1))
            if j < k:
                out[j, 0], out[j, 1], out[j, 2] = x, y, z
        seen += 1
    return filled, seen, squares


@nb.njit(cache=True, nogil=True)
def mark_active(labels, working, editable, flip):  # type: ignore[no-untyped-def]
    """Mark every editable working point (all leave the working set, unless kept later)."""
    for i in range(labels.shape[0]):
        if working[i] and editable[labels[i]]:
            flip[i >> 3] |= np.uint8(1 << (i & 7))


@nb.njit(cache=True, nogil=True)
def keep_inliers_at(  # type: ignore[no-untyped-def]
    xyz, index, labels, working, editable, kind, model, tolerance, region_kind, region, flip
):
    """Clear the marks of the node points that are inliers of the model in the region."""
    for r in range(xyz.shape[0]):
        i = index[r]
        if not (working[i] and editable[labels[i]]):
            continue
        x, y, z = xyz[r, 0], xyz[r, 1], xyz[r, 2]
        if (
            _in_region(region_kind, region, x, y, z)
            and _distance(kind, model, x, y, z) <= tolerance
        ):
            flip[i >> 3] &= np.uint8(~(1 << (i & 7)) & 0xFF)
