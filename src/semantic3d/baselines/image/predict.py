"""Labelling scans with the image baseline: ``.labels``, run record, and face pictures.

:func:`predict_image_scan` resolves the scan's station, runs the shared streaming loop
(:func:`~semantic3d.baselines.common.predict_scan`: any format, labels in the input's point
order, a run record beside them, nothing replaced unless asked) with the model bound to
that station, and writes ``NAME.faces/<face>.png`` beside the labels: colour, ground truth
(when the scan has labels) and prediction side by side (the paper's Figure 2 shows ground
truth above prediction).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semantic3d.baselines.common.prediction import Progress, predict_scan
from semantic3d.baselines.common.run import PredictionRun
from semantic3d.baselines.common.submission import RUN_RECORD_SUFFIX, refuse_existing_outputs
from semantic3d.baselines.image.faces import labels_through_index
from semantic3d.baselines.image.model import ImageModel
from semantic3d.core.errors import Semantic3DError
from semantic3d.viz.cubemap import FACE_NAMES
from semantic3d.viz.cubemap_files import side_by_side, write_png
from semantic3d.viz.station import StationSource, resolve_station

__all__ = ["ImagePrediction", "faces_folder", "predict_image_scan", "prediction_outputs"]

Station = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class ImagePrediction:
    """What labelling one scan produced.

    Attributes:
        run: the run record (labels file, points, time, hardware).
        station: the station used and where it came from.
        faces_dir: the folder of face pictures, or None.
        coverage: share of face pixels showing a point.
    """

    run: PredictionRun
    station: StationSource
    faces_dir: Path | None
    coverage: float


def faces_folder(out_path: str | Path) -> Path:
    """Where the face pictures of ``NAME.labels`` go: ``NAME.faces`` beside it."""
    out = Path(out_path)
    return out.with_name(out.stem + ".faces")


def prediction_outputs(out_path: str | Path, *, with_faces: bool = True) -> list[Path]:
    """Every file :func:`predict_image_scan` writes for ``out_path``."""
    out = Path(out_path)
    paths = [out, out.with_name(out.name + RUN_RECORD_SUFFIX)]
    if with_faces:
        paths += [faces_folder(out) / f"{face}.png" for face in FACE_NAMES]
    return paths


def predict_image_scan(
    model: ImageModel,
    points_path: str | Path,
    *,
    out_path: str | Path,
    station: Station | None = None,
    labels_path: str | Path | None = None,
    write_faces: bool = True,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> ImagePrediction:
    """Label every point of a scan and write its labels, run record and face pictures.

    Args:
        model: a trained image model.
        points_path: the scan (any format).
        out_path: the ``.labels`` file to write.
        station: the scanner position; default the simulator's sidecar, else estimated.
        labels_path: ground truth for the pictures (default the ``.labels`` beside an
            ASCII scan, or the labels in the file).
        write_faces: write ``NAME.faces/``.
        workdir: scratch folder.
        progress: called with points labelled so far.
        overwrite: replace existing outputs.

    Raises:
        OutputExistsError: an output exists and ``overwrite`` is False (checked first).
        Semantic3DError: ``out_path`` is the scan's own ground truth.
    """
    from semantic3d.io.formats import iter_points, sibling_labels_path

    points_path = Path(points_path)
    out = Path(out_path)
    truth = Path(labels_path) if labels_path is not None else sibling_labels_path(points_path)
    if truth is not None and truth.resolve() == out.resolve():
        raise Semantic3DError(
            f"{out}: is the ground truth of {points_path.name}; expected another output path"
        )
    refuse_existing_outputs(prediction_outputs(out, with_faces=write_faces), overwrite=overwrite)
    source = resolve_station(points_path, station=station)
    predictor = model.for_station(source.position, keep_cubemap=True)
    run = predict_scan(
        predictor,
        points_path,
        out_path=out,
        workdir=workdir,
        progress=progress,
        overwrite=overwrite,
    )
    cubemap, predicted = predictor.cubemap, predictor.predicted_faces
    coverage = cubemap.coverage() if cubemap is not None else 0.0
    if not write_faces or cubemap is None or predicted is None:
        return ImagePrediction(run, source, None, coverage)
    images = [cubemap.rgb]
    chunk_size = model.config.faces.chunk_size
    if truth is not None:
        from semantic3d.io.labels import iter_labels

        images.append(
            cubemap.label_image(
                labels_through_index(cubemap.point_index, iter_labels(truth, chunk_size=chunk_size))
            )
        )
    else:
        chunks = iter_points(points_path, chunk_size=chunk_size, sibling_labels=False)
        first = next(iter(iter_points(points_path, chunk_size=1, sibling_labels=False)), None)
        if first is not None and first.labels is not None:
            label_chunks = (c.labels for c in chunks if c.labels is not None)
            images.append(
                cubemap.label_image(labels_through_index(cubemap.point_index, label_chunks))
            )
    images.append(cubemap.label_image(predicted))
    folder = faces_folder(out)
    folder.mkdir(parents=True, exist_ok=True)
    for number, face in enumerate(FACE_NAMES):
        write_png(folder / f"{face}.png", side_by_side(*(np.asarray(i[number]) for i in images)))
    return ImagePrediction(run, source, folder, coverage)
