"""Scale-out: the library's tile jobs and per-scan jobs mapped over a Dask cluster.

Nothing here imports Dask until a cluster is opened (extra ``dask``); see ``docs/scale.md``.

>>> from semantic3d.scale import ClusterSpec
>>> ClusterSpec(n_workers=2).threads_per_worker
1
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.scale.cluster import ClusterError, ClusterSpec, DaskCluster, connect
    from semantic3d.scale.convert import convert_files_on_cluster
    from semantic3d.scale.evaluation import (
        compute_label_agreement_on_cluster,
        evaluate_submission_on_cluster,
    )
    from semantic3d.scale.predict import (
        ClusterPredictor,
        predict_scan_on_cluster,
        predict_scans_on_cluster,
    )
    from semantic3d.scale.simulate import simulate_on_cluster
    from semantic3d.scale.training import (
        build_training_set_on_cluster,
        train_covariance_model_on_cluster,
    )

__all__ = [
    "ClusterError",
    "ClusterPredictor",
    "ClusterSpec",
    "DaskCluster",
    "build_training_set_on_cluster",
    "compute_label_agreement_on_cluster",
    "connect",
    "convert_files_on_cluster",
    "evaluate_submission_on_cluster",
    "predict_scan_on_cluster",
    "predict_scans_on_cluster",
    "simulate_on_cluster",
    "train_covariance_model_on_cluster",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "ClusterError": "semantic3d.scale.cluster",
        "ClusterSpec": "semantic3d.scale.cluster",
        "DaskCluster": "semantic3d.scale.cluster",
        "connect": "semantic3d.scale.cluster",
        "compute_label_agreement_on_cluster": "semantic3d.scale.evaluation",
        "evaluate_submission_on_cluster": "semantic3d.scale.evaluation",
        "ClusterPredictor": "semantic3d.scale.predict",
        "predict_scan_on_cluster": "semantic3d.scale.predict",
        "predict_scans_on_cluster": "semantic3d.scale.predict",
        "convert_files_on_cluster": "semantic3d.scale.convert",
        "simulate_on_cluster": "semantic3d.scale.simulate",
        "build_training_set_on_cluster": "semantic3d.scale.training",
        "train_covariance_model_on_cluster": "semantic3d.scale.training",
    },
)
