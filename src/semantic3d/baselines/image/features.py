"""Dense per-pixel descriptors of a colour face, as in associative hierarchical fields.

Four kinds, each computed for every pixel of an ``(h, w, 3)`` uint8 image:

- ``texton``: the 17-filter bank of Winn et al. (2005) used by TextonBoost and ALE on CIELab
  (Gaussians σ = 1, 2, 4 on L, a, b; Laplacians of Gaussian σ = 1, 2, 4, 8 on L; x and y
  derivatives of Gaussian σ = 2, 4 on L), scipy.ndimage filters;
- ``sift``: dense SIFT-like DAISY descriptors (scikit-image), computed on a grid of
  ``daisy_step`` pixels and given to every pixel of the grid cell (what dense SIFT does
  with its sampling step);
- ``ltp_upper`` / ``ltp_lower``: local ternary patterns (Tan & Triggs 2010): the eight
  neighbours at radius 1 compared with the centre ± a threshold, as two 8-bit codes. They
  are quantised by construction, so they are words already (256 each);
- ``selfsim``: local self-similarity (Shechtman & Irani 2007): the sum of squared
  differences between the 5 × 5 patch at the pixel and the patches at 24 log-polar offsets
  (3 radii × 8 angles), turned into correlations ``exp(-ssd / max(noise, ssd_min))`` and
  scaled to a maximum of 1.

Continuous descriptors become words with k-means (:mod:`~semantic3d.baselines.image.words`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import require

__all__ = [
    "CODE_KINDS",
    "CONTINUOUS_KINDS",
    "compute_descriptors",
    "compute_ltp",
    "compute_self_similarity",
    "compute_sift",
    "compute_textons",
    "rgb_to_lab",
]

CONTINUOUS_KINDS = ("texton", "sift", "selfsim")
"""Descriptor kinds clustered into words."""
CODE_KINDS = ("ltp_upper", "ltp_lower")
"""Descriptor kinds that are words already (256 codes each)."""

_LTP_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1))
_SELFSIM_RADII = (2, 4, 8)
_SELFSIM_ANGLES = 8
_SELFSIM_PATCH = 5


@dataclass(frozen=True, slots=True)
class Descriptors:
    """Dense descriptors of one image.

    Attributes:
        continuous: kind -> ``(h, w, d)`` float32 descriptors (``texton``, ``sift``,
            ``selfsim``).
        codes: kind -> ``(h, w)`` int16 words (``ltp_upper``, ``ltp_lower``).
        lab: ``(h, w, 3)`` float32 CIELab colour.
    """

    continuous: dict[str, NDArray[np.float32]]
    codes: dict[str, NDArray[np.int16]]
    lab: NDArray[np.float32]


def rgb_to_lab(image: NDArray[np.uint8]) -> NDArray[np.float32]:
    """CIELab of an ``(h, w, 3)`` uint8 image (scikit-image)."""
    color = require("skimage.color", "image")
    return np.asarray(color.rgb2lab(image), np.float32)  # type: ignore[attr-defined]


def compute_textons(lab: NDArray[np.float32]) -> NDArray[np.float32]:
    """``(h, w, 17)`` filter-bank responses of a CIELab image."""
    ndimage = require("scipy.ndimage", "image")
    responses: list[NDArray[np.float64]] = []
    for sigma in (1.0, 2.0, 4.0):
        for channel in range(3):
            responses.append(ndimage.gaussian_filter(lab[..., channel], sigma))  # type: ignore[attr-defined]
    lightness = lab[..., 0].astype(np.float64)
    for sigma in (1.0, 2.0, 4.0, 8.0):
        responses.append(ndimage.gaussian_laplace(lightness, sigma))  # type: ignore[attr-defined]
    for sigma in (2.0, 4.0):
        responses.append(ndimage.gaussian_filter(lightness, sigma, order=(0, 1)))  # type: ignore[attr-defined]
        responses.append(ndimage.gaussian_filter(lightness, sigma, order=(1, 0)))  # type: ignore[attr-defined]
    return np.stack(responses, axis=-1).astype(np.float32)


def compute_sift(gray: NDArray[np.float64], *, step: int, radius: int) -> NDArray[np.float32]:
    """``(h, w, 104)`` DAISY descriptors, one per grid cell of ``step`` pixels, per pixel."""
    feature = require("skimage.feature", "image")
    height, width = gray.shape
    padded = np.pad(gray, radius, mode="reflect")
    grid = feature.daisy(  # type: ignore[attr-defined]
        padded, step=step, radius=radius, rings=2, histograms=6, orientations=8
    )
    rows = np.minimum(np.arange(height) // step, grid.shape[0] - 1)
    cols = np.minimum(np.arange(width) // step, grid.shape[1] - 1)
    return np.asarray(grid[rows][:, cols], np.float32)


def compute_ltp(
    gray: NDArray[np.float64], *, threshold: float
) -> tuple[NDArray[np.int16], NDArray[np.int16]]:
    """Upper and lower local ternary pattern codes (``(h, w)``, 0..255) of a 0..255 image."""
    padded = np.pad(gray, 1, mode="edge")
    height, width = gray.shape
    upper = np.zeros((height, width), np.int16)
    lower = np.zeros((height, width), np.int16)
    for bit, (dy, dx) in enumerate(_LTP_OFFSETS):
        neighbour = padded[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width]
        upper |= (neighbour > gray + threshold).astype(np.int16) << bit
        lower |= (neighbour < gray - threshold).astype(np.int16) << bit
    return upper, lower


def compute_self_similarity(gray: NDArray[np.float64]) -> NDArray[np.float32]:
    """``(h, w, 24)`` local self-similarity descriptors of a 0..1 image."""
    ndimage = require("scipy.ndimage", "image")
    margin = max(_SELFSIM_RADII)
    padded = np.pad(gray, margin, mode="reflect")
    height, width = gray.shape
    ssd: list[NDArray[np.float64]] = []
    for radius in _SELFSIM_RADII:
        for k in range(_SELFSIM_ANGLES):
            angle = 2 * math.pi * k / _SELFSIM_ANGLES
            dy, dx = round(radius * math.sin(angle)), round(radius * math.cos(angle))
            shifted = padded[margin + dy : margin + dy + height, margin + dx : margin + dx + width]
            ssd.append(ndimage.uniform_filter((gray - shifted) ** 2, _SELFSIM_PATCH))  # type: ignore[attr-defined]
    stack = np.stack(ssd, axis=-1)
    noise = max(float(np.median(stack)), 1e-4)
    correlation = np.exp(-stack / np.maximum(noise, stack.min(axis=-1, keepdims=True)))
    correlation /= np.maximum(correlation.max(axis=-1, keepdims=True), 1e-6)
    return correlation.astype(np.float32)


def compute_descriptors(
    image: NDArray[np.uint8], *, daisy_step: int, daisy_radius: int, ltp_threshold: float
) -> Descriptors:
    """Every descriptor kind of an ``(h, w, 3)`` uint8 image."""
    lab = rgb_to_lab(image)
    gray01 = image.astype(np.float64).mean(axis=-1) / 255.0
    upper, lower = compute_ltp(gray01 * 255.0, threshold=ltp_threshold)
    return Descriptors(
        continuous={
            "texton": compute_textons(lab),
            "sift": compute_sift(gray01, step=daisy_step, radius=daisy_radius),
            "selfsim": compute_self_similarity(gray01),
        },
        codes={"ltp_upper": upper, "ltp_lower": lower},
        lab=lab,
    )
