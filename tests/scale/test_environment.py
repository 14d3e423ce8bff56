"""Starting local workers leaves this process's environment, and so its thread budget, as
it was; the workers get their thread counts and, in a quiet run, Dask's quiet logs."""

from __future__ import annotations

import logging
import os
import sys

import cloudpickle
import pytest

from semantic3d.core.threads import thread_budget
from semantic3d.scale.cluster import THREAD_VARIABLES, ClusterSpec, connect

pytestmark = pytest.mark.slow

# Functions of this module run on the workers, which cannot import the tests package.
cloudpickle.register_pickle_by_value(sys.modules[__name__])

# Dask's nanny writes its pre-spawn variables into the starting process's environment.
WATCHED = (
    *THREAD_VARIABLES,
    "MALLOC_TRIM_THRESHOLD_",
    "PYTHONHASHSEED",
    "DASK_LOGGING__DISTRIBUTED",
)


def _worker_view() -> tuple[dict[str, str | None], int]:
    variables = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    return variables, logging.getLogger("distributed.worker").getEffectiveLevel()


def test_local_workers_leave_this_process_s_environment_and_budget_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for name in WATCHED:
        monkeypatch.delenv(name, raising=False)
    budget = thread_budget()
    with connect(ClusterSpec(n_workers=1, threads_per_worker=1)) as cluster:
        during = {name: os.environ.get(name) for name in WATCHED}
        assert thread_budget() == budget  # Dask's OMP_NUM_THREADS=1 once made it 1
        seen = list(cluster.client.run(_worker_view).values())
    assert during == dict.fromkeys(WATCHED)
    assert {name: os.environ.get(name) for name in WATCHED} == dict.fromkeys(WATCHED)
    variables, level = seen[0]
    assert variables == dict.fromkeys(THREAD_VARIABLES, "1")  # the worker's own count
    assert level >= logging.CRITICAL  # a quiet run: a lost heartbeat at shutdown prints nothing
