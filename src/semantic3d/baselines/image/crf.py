"""The CRF of the image baseline: pixel and superpixel potentials, solved with graph cuts.

Energy over the class ``x_p`` of every pixel::

    E(x) = Σ_p -log P(x_p | p)                                  pixel potentials
         + w_s / L Σ_levels Σ_p -log P̄_level(x_p | segment(p))  superpixel potentials
         + w_pair Σ_(p,q) exp(-β |Lab_p - Lab_q|²) [x_p ≠ x_q]   contrast-sensitive Potts

``P`` is the boosted classifier's posterior, ``P̄`` its mean over a superpixel of one of
the ``L`` segmentations (scikit-image quickshift / SLIC / felzenszwalb at coarse-to-fine
settings), ``β = 1 / (2 mean |ΔLab|²)``. Associative hierarchical fields attach
auxiliary superpixel variables with robust P^n potentials to the pixels; taking each
superpixel's potential as a unary term on its pixels keeps the energy pairwise and
metric, so alpha-expansion solves it with one max-flow (PyMaxflow) per class and cycle.
PyMaxflow's own ``aexpansion_grid`` takes one pairwise matrix for every edge, so the
contrast-sensitive weights need the expansion graphs built here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import require

__all__ = ["alpha_expansion", "compute_superpixels", "contrast_weights", "superpixel_unary"]

_EPS = 1e-6


def compute_superpixels(
    image: NDArray[np.uint8], *, method: str, scales: Sequence[float], seed: int = 0
) -> list[NDArray[np.int64]]:
    """One ``(h, w)`` segment map per setting of ``scales``."""
    segmentation = require("skimage.segmentation", "image")
    maps: list[NDArray[np.int64]] = []
    for scale in scales:
        if method == "quickshift":
            segments = segmentation.quickshift(  # type: ignore[attr-defined]
                image, kernel_size=scale, max_dist=4 * scale, ratio=0.5, rng=seed
            )
        elif method == "slic":
            segments = segmentation.slic(  # type: ignore[attr-defined]
                image, n_segments=int(scale), compactness=10, start_label=0
            )
        else:
            segments = segmentation.felzenszwalb(image, scale=scale, sigma=0.8, min_size=20)  # type: ignore[attr-defined]
        maps.append(np.asarray(segments, np.int64))
    return maps


def superpixel_unary(
    proba: NDArray[np.float32], segments: NDArray[np.int64]
) -> NDArray[np.float32]:
    """``(h, w, k)``: -log of the mean posterior of each pixel's segment."""
    height, width, n_classes = proba.shape
    flat = segments.reshape(-1)
    n_segments = int(flat.max()) + 1
    sums = np.zeros((n_segments, n_classes), np.float64)
    np.add.at(sums, flat, proba.reshape(-1, n_classes))
    counts = np.bincount(flat, minlength=n_segments)[:, None]
    mean = sums / np.maximum(counts, 1)
    return (-np.log(mean[flat] + _EPS)).reshape(height, width, n_classes).astype(np.float32)


def contrast_weights(
    lab: NDArray[np.float32], *, weight: float
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Potts weights of horizontal ``(h, w-1)`` and vertical ``(h-1, w)`` neighbour pairs."""
    horizontal = ((lab[:, 1:] - lab[:, :-1]) ** 2).sum(axis=-1)
    vertical = ((lab[1:] - lab[:-1]) ** 2).sum(axis=-1)
    mean = (horizontal.sum() + vertical.sum()) / max(horizontal.size + vertical.size, 1)
    beta = 1.0 / (2.0 * max(float(mean), _EPS))
    return (
        (weight * np.exp(-beta * horizontal)).astype(np.float32),
        (weight * np.exp(-beta * vertical)).astype(np.float32),
    )


def alpha_expansion(
    unary: NDArray[np.float32],
    horizontal: NDArray[np.float32],
    vertical: NDArray[np.float32],
    *,
    n_cycles: int,
) -> NDArray[np.int64]:
    """Minimise unary + contrast-sensitive Potts energy on a 4-connected grid.

    Args:
        unary: ``(h, w, k)`` cost of each class at each pixel.
        horizontal, vertical: Potts weights of the pairs ``(r, c)-(r, c+1)`` and
            ``(r, c)-(r+1, c)``.
        n_cycles: passes over the classes (stops early when a pass changes nothing).

    Returns:
        ``(h, w)`` class numbers (columns of ``unary``).
    """
    maxflow = require("maxflow", "image")
    height, width, n_classes = unary.shape
    labels = np.argmin(unary, axis=-1)
    rows, cols = np.indices((height, width))
    right = np.zeros((3, 3))
    right[1, 2] = 1
    down = np.zeros((3, 3))
    down[2, 1] = 1
    for _ in range(n_cycles):
        changed = False
        for alpha in range(n_classes):
            graph = maxflow.Graph[float]()  # type: ignore[attr-defined]
            nodes = graph.add_grid_nodes((height, width))
            cost_keep = unary[rows, cols, labels].astype(np.float64)
            cost_alpha = unary[..., alpha].astype(np.float64).copy()
            for weights, first, second, structure in (
                (horizontal, np.s_[:, :-1], np.s_[:, 1:], right),
                (vertical, np.s_[:-1, :], np.s_[1:, :], down),
            ):
                lp, lq = labels[first], labels[second]
                e00 = weights * (lp != lq)
                e01 = weights * (lp != alpha)
                e10 = weights * (lq != alpha)
                # E(xp, xq) = e00 + (e10 - e00) xp + (0 - e10) xq + (e01 + e10 - e00) (1 - xp) xq
                cost_alpha[first] += e10 - e00
                cost_alpha[second] -= e10
                full = np.zeros((height, width))
                full[first] = e01 + e10 - e00
                graph.add_grid_edges(nodes, weights=full, structure=structure, symmetric=False)
            low = np.minimum(cost_keep, cost_alpha)
            graph.add_grid_tedges(nodes, cost_alpha - low, cost_keep - low)
            graph.maxflow()
            take = graph.get_grid_segments(nodes) & (labels != alpha)
            if take.any():
                labels = np.where(take, alpha, labels)
                changed = True
        if not changed:
            break
    return labels.astype(np.int64)


def grid_energy(
    labels: NDArray[np.int64],
    unary: NDArray[np.float32],
    horizontal: NDArray[np.float32],
    vertical: NDArray[np.float32],
) -> float:
    """The energy :func:`alpha_expansion` minimises, of a labelling."""
    rows, cols = np.indices(labels.shape)
    total = float(unary[rows, cols, labels].sum())
    total += float((horizontal * (labels[:, 1:] != labels[:, :-1])).sum())
    total += float((vertical * (labels[1:] != labels[:-1])).sum())
    return total
