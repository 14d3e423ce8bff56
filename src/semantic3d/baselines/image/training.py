"""Training the image baseline: render each labelled scan's cube map, fit a segmenter.

Each training scan is rendered from its station (given, the simulator's sidecar, or
estimated: :func:`~semantic3d.viz.station.resolve_station`) at the configuration's face
size, with its labels; the label faces, class 7 removed, train either variant.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence

from semantic3d import __version__
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.baselines.image.config import ImageConfig
from semantic3d.baselines.image.faces import Face, cube_faces
from semantic3d.baselines.image.model import ImageModel, ImageVariant, Segmenter
from semantic3d.viz.cubemap import CubeMap, render_cubemap
from semantic3d.viz.station import StationSource, resolve_station

__all__ = ["render_scan", "train_image_model"]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``."""

Station = tuple[float, float, float]


def render_scan(
    scan: LabelledScan, *, config: ImageConfig, station: Station | None = None
) -> tuple[CubeMap, StationSource]:
    """The labelled cube map of a training scan and where its station came from."""
    faces = config.faces
    source = resolve_station(
        scan.points_path,
        station=station,
        chunks=scan.iter_points(chunk_size=faces.chunk_size),
    )
    cubemap = render_cubemap(
        scan.iter_points(chunk_size=faces.chunk_size),
        station=source.position,
        size=faces.size,
        splat_radius_px=faces.splat_radius_px,
    )
    return cubemap, source


def train_image_model(
    scans: Sequence[LabelledScan],
    *,
    config: ImageConfig,
    variant: ImageVariant = ImageVariant.BOOSTED,
    stations: Mapping[str, Station] | None = None,
    progress: Progress | None = None,
) -> ImageModel:
    """Render every training scan and fit the ``variant`` segmenter on their faces.

    Raises:
        TrainingDataError: no scan, or the faces hold fewer than two classes.
    """
    if not scans:
        raise TrainingDataError("training: expected at least one labelled scan, found none")
    started = time.perf_counter()
    faces: list[Face] = []
    used: list[Station] = []
    for number, scan in enumerate(scans):
        cubemap, source = render_scan(scan, config=config, station=(stations or {}).get(scan.name))
        logger.info("%s: station %s (%s)", scan.name, source.position, source.source)
        used.append(source.position)
        faces += cube_faces(cubemap)
        if progress is not None:
            progress("rendering", number + 1, len(scans))
    segmenter: Segmenter
    try:
        if variant is ImageVariant.UNET:
            from semantic3d.baselines.image.unet import UNetSegmenter

            segmenter = UNetSegmenter(config).fit(faces, progress=progress)
        else:
            from semantic3d.baselines.image.segmenter import BoostedSegmenter

            segmenter = BoostedSegmenter(config).fit(faces, progress=progress)
    except ValueError as exc:
        names = ", ".join(scan.name for scan in scans)
        raise TrainingDataError(f"{names}: {exc}") from None
    return ImageModel(
        variant=ImageVariant(variant),
        segmenter=segmenter,
        config=config,
        training_scans=tuple(scan.name for scan in scans),
        training_stations=tuple(used),
        package_version=__version__,
        training_time_s=time.perf_counter() - started,
    )
