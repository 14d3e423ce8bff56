"""Many point files converted, one task per file, on a Dask cluster.

Each worker reads its source and writes its destination itself, through the same
:func:`semantic3d.io.conversion.convert_file` as the single-process path (staged under a
hidden name, renamed when complete): the files are byte for byte those the
single-process path writes. Sources and destinations must be at paths the workers see.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path

from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE
from semantic3d.io.conversion import ConvertedFile, convert_file
from semantic3d.scale.cluster import DaskCluster, MapProgress, map_items

__all__ = ["convert_files_on_cluster"]

ConvertJob = tuple[Path, Path]
"""``(source, destination)``."""


def convert_files_on_cluster(
    jobs: Sequence[tuple[str | Path, str | Path]],
    *,
    cluster: DaskCluster | None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    crs: str | None = None,
    progress: MapProgress | None = None,
) -> list[ConvertedFile]:
    """Convert every ``(source, destination)`` pair, one task each; results in input order.

    ``cluster`` None runs the tasks in this process. ``progress(files_done, files_total)``.

    Raises:
        ClusterError: a task failed on every try (a library error is raised as itself).
    """
    pairs = [(Path(source), Path(destination)) for source, destination in jobs]
    task = partial(_convert_job, chunk_size=chunk_size, crs=crs)
    return list(map_items(cluster, task, pairs, progress=progress))


def _convert_job(job: ConvertJob, *, chunk_size: int, crs: str | None) -> ConvertedFile:
    source, destination = job
    return convert_file(source, destination, chunk_size=chunk_size, crs=crs)
