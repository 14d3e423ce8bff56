"""``--scheduler`` / ``--workers``: the options of the commands that can run on a Dask cluster.

Without either option a command runs in this process and Dask is not imported. With
``--scheduler tcp://HOST:8786`` it uses a running cluster; with ``--workers N`` it starts
N worker processes on this machine for the command and stops them after it. The
dashboard's address is printed on stderr.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import escape

if TYPE_CHECKING:
    from semantic3d.scale.cluster import DaskCluster

SCHEDULER_HELP = (
    "Run on the Dask cluster of this scheduler (tcp://HOST:8786); inputs, outputs and scratch "
    "folders must be visible to its workers at the same paths (extra: dask)."
)
WORKERS_HELP = "Run on this many local Dask worker processes, started for the command."


def scheduler_option() -> Any:
    """The ``--scheduler`` option."""
    return typer.Option(None, "--scheduler", metavar="ADDRESS", help=SCHEDULER_HELP)


def workers_option() -> Any:
    """The ``--workers`` option."""
    return typer.Option(None, "--workers", min=1, help=WORKERS_HELP)


@contextmanager
def open_cluster(scheduler: str | None, workers: int | None) -> Iterator[DaskCluster | None]:
    """The cluster the options name, or None for this process (Dask not imported)."""
    if scheduler is None and workers is None:
        yield None
        return
    from semantic3d.scale.cluster import ClusterSpec, connect

    spec = ClusterSpec(scheduler=scheduler, n_workers=workers)
    with connect(spec) as cluster:
        where = scheduler if scheduler is not None else f"{workers} local worker processes"
        dashboard = cluster.dashboard_link or "none"
        ui.err_console.print(
            f"Dask: {escape(where)}, dashboard {escape(dashboard)}", highlight=False
        )
        yield cluster
