"""``ImageModel``: a trained image segmenter with what is needed to label a scan with it.

Labelling a scan (:class:`StationPredictor`, the shared prediction loop's
:class:`~semantic3d.baselines.common.Predictor`): the streamed points are rendered onto
the cube faces around the station while each point's pixel is written to a scratch file;
the faces are segmented; then every point takes the class of the pixel it projects to
(the pixel showing it, or, for a point hidden behind a nearer one, the pixel it is
hidden behind), read back from the scratch file a chunk at a time.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import LabelledBlock
from semantic3d.baselines.image.config import ImageConfig
from semantic3d.baselines.image.faces import Face, cube_faces, tee_pixels
from semantic3d.core.pointcloud import PointCloud
from semantic3d.viz.cubemap import CubeMap, render_cubemap

__all__ = ["ImageModel", "ImageVariant", "Segmenter", "StationPredictor"]


class ImageVariant(StrEnum):
    """Which segmenter: the paper's boosted pixels + CRF, or the encoder-decoder."""

    BOOSTED = "boosted"
    UNET = "unet"


class Segmenter(Protocol):
    """What both variants offer: label values of a face, and the classes they predict."""

    classes_: NDArray[np.uint8]

    def segment(self, face: Face) -> NDArray[np.uint8]:
        """``(s, s)`` label values (0 where no point is shown)."""
        ...


@dataclass(frozen=True, slots=True)
class ImageModel:
    """A trained image baseline.

    Attributes:
        variant: which segmenter.
        segmenter: the fitted segmenter.
        config: the resolved configuration.
        training_scans: names of the training scans.
        training_stations: their stations.
        package_version: semantic3d version that trained it.
        training_time_s: wall time of rendering and fitting.
    """

    variant: ImageVariant
    segmenter: Segmenter
    config: ImageConfig
    training_scans: tuple[str, ...]
    training_stations: tuple[tuple[float, float, float], ...]
    package_version: str
    training_time_s: float

    @property
    def label_values(self) -> tuple[int, ...]:
        """Label values it predicts."""
        return tuple(int(v) for v in self.segmenter.classes_)

    def segment_cubemap(self, cubemap: CubeMap) -> NDArray[np.uint8]:
        """``(6, s, s)`` predicted label values of a cube map's faces."""
        return np.stack([self.segmenter.segment(face) for face in cube_faces(cubemap)])

    def for_station(
        self, station: tuple[float, float, float], *, keep_cubemap: bool = False
    ) -> StationPredictor:
        """A predictor labelling scans taken from ``station``."""
        return StationPredictor(self, station, keep_cubemap=keep_cubemap)


@dataclass(slots=True)
class StationPredictor:
    """An :class:`ImageModel` bound to a station: the prediction loop's ``Predictor``.

    After a scan, ``cubemap`` and ``predicted_faces`` hold its faces when ``keep_cubemap``.
    """

    model: ImageModel
    station: tuple[float, float, float]
    keep_cubemap: bool = False
    cubemap: CubeMap | None = field(default=None, init=False)
    predicted_faces: NDArray[np.uint8] | None = field(default=None, init=False)

    @property
    def training_scans(self) -> tuple[str, ...]:
        """The model's training scans."""
        return self.model.training_scans

    @property
    def chunk_size(self) -> int:
        """Points per chunk read."""
        return self.model.config.faces.chunk_size

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Render, segment, and give every point its pixel's class, chunk by chunk."""
        faces = self.model.config.faces
        pixels_path = workdir / "pixels.i32"
        cubemap = render_cubemap(
            tee_pixels(chunks, station=self.station, size=faces.size, path=pixels_path),
            station=self.station,
            size=faces.size,
            splat_radius_px=faces.splat_radius_px,
            with_labels=False,
        )
        predicted = self.model.segment_cubemap(cubemap)
        if self.keep_cubemap:
            self.cubemap, self.predicted_faces = cubemap, predicted
        flat_labels = predicted.reshape(-1)
        shown = flat_labels[cubemap.has_point.reshape(-1)]
        counts = np.bincount(shown, minlength=256)
        counts[0] = 0
        fallback = np.uint8(np.argmax(counts)) if counts.any() else self.model.segmenter.classes_[0]
        n_points = cubemap.n_points
        if n_points == 0:
            return
        pixels = np.memmap(pixels_path, dtype=np.int32, mode="r", shape=(n_points,))
        step = self.chunk_size
        for begin in range(0, n_points, step):
            flat = np.asarray(pixels[begin : begin + step])
            labels = np.where(flat >= 0, flat_labels[np.maximum(flat, 0)], fallback)
            labels[labels == 0] = fallback
            yield LabelledBlock(
                np.arange(begin, begin + flat.size, dtype=np.int64),
                labels.astype(np.uint8),
                n_points,
            )
        del pixels
