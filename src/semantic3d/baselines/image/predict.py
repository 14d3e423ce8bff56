"""Labelling scans with the image baseline: ``.labels``, run record, and face pictures.

:func:`predict_image_scan` resolves the scan's station, runs the shared streaming loop
(:func:`~semantic3d.baselines.common.predict_scan`: any format, labels in the input's point
order, a run record beside them, nothing replaced unless asked) with the model bound to
that station, and when asked writes ``FACES_DIR/NAME/<face>.png``: colour, ground truth
(when the scan has labels) and prediction side by side (the paper's Figure 2 shows ground
truth above prediction). :func:`predict_image_scans` labels many scans into a folder or a
submission zip, as every baseline's ``predict`` does.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from semantic3d.baselines.common.prediction import (
    Progress,
    RunProgress,
    predict_scan,
    write_prediction_set,
)
from semantic3d.baselines.common.run import PredictionRun, PredictionRunSet
from semantic3d.baselines.common.submission import (
    RUN_RECORD_SUFFIX,
    ScanToLabel,
    refuse_existing_outputs,
    refuse_ground_truth_outputs,
    refuse_unsafe_outputs,
)
from semantic3d.baselines.image.faces import labels_through_index
from semantic3d.baselines.image.model import ImageModel
from semantic3d.core.errors import GroundTruthOutputError
from semantic3d.viz.cubemap import FACE_NAMES
from semantic3d.viz.cubemap_files import side_by_side, write_png
from semantic3d.viz.station import StationSource, resolve_station

__all__ = [
    "ImagePrediction",
    "ImagePredictionSet",
    "faces_folder",
    "predict_image_scan",
    "predict_image_scans",
    "prediction_outputs",
]

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


def faces_folder(faces_dir: str | Path, points_path: str | Path) -> Path:
    """Where the face pictures of a scan go: ``FACES_DIR/NAME`` for the scan ``NAME.txt``."""
    return Path(faces_dir) / Path(points_path).stem


def prediction_outputs(out_path: str | Path, *, faces: Path | None = None) -> list[Path]:
    """Every file :func:`predict_image_scan` writes for ``out_path`` (and, with ``faces``,
    the scan's face folder)."""
    out = Path(out_path)
    paths = [out, out.with_name(out.name + RUN_RECORD_SUFFIX)]
    if faces is not None:
        paths += [faces / f"{face}.png" for face in FACE_NAMES]
    return paths


@dataclass(frozen=True, slots=True)
class ImagePredictionSet:
    """What labelling many scans produced: the runs (folder or zip) and each scan's result."""

    runs: PredictionRunSet
    scans: tuple[ImagePrediction, ...]


def predict_image_scans(
    model: ImageModel,
    scans: Sequence[ScanToLabel],
    out: str | Path,
    *,
    station: Station | None = None,
    faces_dir: str | Path | None = None,
    workdir: str | Path | None = None,
    progress: RunProgress | None = None,
    overwrite: bool = False,
) -> ImagePredictionSet:
    """Label ``scans`` into a folder, or a zip archive when ``out`` ends in .zip, as every
    baseline does (:func:`~semantic3d.baselines.common.prediction.predict_scans`), each
    from its own station; with ``faces_dir``, each scan's face pictures go to
    ``FACES_DIR/NAME/``.

    Raises:
        GroundTruthOutputError: an output is a scan's ground truth (even with overwrite).
        OutputExistsError: an output exists and ``overwrite`` is False (checked first).
        ValueError: ``station`` given for more than one scan.
    """
    if station is not None and len(scans) > 1:
        raise ValueError(f"station: applies to one scan, found {len(scans)}")
    started = time.perf_counter()
    out = Path(out)
    refuse_unsafe_outputs(out, scans, overwrite=overwrite)
    faces = None if faces_dir is None else Path(faces_dir)
    if faces is not None:
        pictures = [
            faces_folder(faces, scan.points_path) / f"{face}.png"
            for scan in scans
            for face in FACE_NAMES
        ]
        refuse_existing_outputs(pictures, overwrite=overwrite)
    runs: list[PredictionRun] = []
    results: list[ImagePrediction] = []

    def label_all(folder: Path) -> None:
        for index, scan in enumerate(scans):
            result = predict_image_scan(
                model,
                scan.points_path,
                out_path=folder / scan.output_name,
                station=station,
                faces_dir=faces,
                workdir=workdir,
                progress=None if progress is None else partial(_scan_progress, progress, index),
                overwrite=overwrite or folder != out,
            )
            runs.append(result.run)
            results.append(result)

    written = write_prediction_set(out, scans, label_all, started=started, runs=runs)
    return ImagePredictionSet(written, tuple(results))


def _scan_progress(progress: RunProgress, index: int, done: int, total: int) -> None:
    progress(index, done, total)


def predict_image_scan(
    model: ImageModel,
    points_path: str | Path,
    *,
    out_path: str | Path,
    station: Station | None = None,
    labels_path: str | Path | None = None,
    faces_dir: str | Path | None = None,
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
        faces_dir: write the face pictures (colour | truth | prediction) into
            ``FACES_DIR/NAME/``; none by default.
        workdir: scratch folder.
        progress: called with points labelled so far.
        overwrite: replace existing outputs.

    Raises:
        OutputExistsError: an output exists and ``overwrite`` is False (checked first).
        GroundTruthOutputError: ``out_path`` is the scan's own ground truth (refused even
            with ``overwrite``).
    """
    from semantic3d.io.formats import iter_points, sibling_labels_path

    points_path = Path(points_path)
    out = Path(out_path)
    truth = Path(labels_path) if labels_path is not None else sibling_labels_path(points_path)
    folder = None if faces_dir is None else faces_folder(faces_dir, points_path)
    outputs = prediction_outputs(out, faces=folder)
    refuse_ground_truth_outputs([points_path], outputs)
    if truth is not None and truth.resolve() in {path.resolve() for path in outputs}:
        raise GroundTruthOutputError(
            f"{out}: is the ground truth of {points_path.name}; expected another output path"
        )
    refuse_existing_outputs(outputs, overwrite=overwrite)
    source = resolve_station(points_path, station=station)
    predictor = model.for_station(source.position, keep_cubemap=folder is not None)
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
    if folder is None or cubemap is None or predicted is None:
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
    folder.mkdir(parents=True, exist_ok=True)
    for number, face in enumerate(FACE_NAMES):
        write_png(folder / f"{face}.png", side_by_side(*(np.asarray(i[number]) for i in images)))
    return ImagePrediction(run, source, folder, coverage)
