"""``--workers`` / ``--scheduler`` on the commands: same output as without them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.scale.cluster import DaskCluster

runner = CliRunner()


def _truth_and_prediction(scan_dir: Path, tmp_path: Path) -> tuple[Path, Path]:
    truth, pred = tmp_path / "truth", tmp_path / "pred"
    truth.mkdir()
    pred.mkdir()
    for name in ("test", "other"):
        shutil.copy(scan_dir / f"{name}.labels", truth)
        values = np.loadtxt(scan_dir / f"{name}.labels", dtype=np.int64)
        values[::7] = 1
        (pred / f"{name}.labels").write_text("\n".join(map(str, values)) + "\n")
    return truth, pred


def test_evaluate_on_a_running_scheduler(
    cluster: DaskCluster, scan_dir: Path, tmp_path: Path
) -> None:
    truth, pred = _truth_and_prediction(scan_dir, tmp_path)
    plain = runner.invoke(
        app, ["evaluate", "--gt", str(truth), "--pred", str(pred), "--json", str(tmp_path / "a")]
    )
    assert plain.exit_code == 0, plain.output
    local = runner.invoke(
        app,
        [
            "evaluate",
            "--gt",
            str(truth),
            "--pred",
            str(pred),
            "--json",
            str(tmp_path / "b"),
            "--scheduler",
            cluster.client.scheduler.address,
        ],
    )
    assert local.exit_code == 0, local.output
    assert f"Dask: {cluster.client.scheduler.address}, dashboard http" in local.output
    assert (tmp_path / "a").read_bytes() == (tmp_path / "b").read_bytes()
    assert json.loads((tmp_path / "b").read_text())["n_points"] > 0


def test_agreement_on_a_running_scheduler(
    cluster: DaskCluster, scan_dir: Path, tmp_path: Path
) -> None:
    files = [
        str(scan_dir / f"{name}.{kind}") for name in ("test", "other") for kind in ("txt", "labels")
    ]
    settings = ["--max-distance", "0.15", "--tile-size", "6"]
    plain = runner.invoke(app, ["agreement", *files, *settings])
    address = cluster.client.scheduler.address
    remote = runner.invoke(
        app, ["agreement", *files, *settings, "--scheduler", address, "--workdir", str(tmp_path)]
    )
    assert plain.exit_code == remote.exit_code == 0, remote.output
    assert f"Dask: {address}" in remote.output
    assert plain.stdout == remote.stdout  # the same table


def test_both_options_are_refused(scan_dir: Path, tmp_path: Path) -> None:
    truth, pred = _truth_and_prediction(scan_dir, tmp_path)
    result = runner.invoke(
        app,
        [
            "evaluate",
            "--gt",
            str(truth),
            "--pred",
            str(pred),
            "--workers",
            "1",
            "--scheduler",
            "tcp://127.0.0.1:1",
        ],
    )
    assert result.exit_code == 2
    assert "expected a scheduler address or a number of workers, found both" in result.output


def test_without_options_dask_is_not_imported(scan_dir: Path, tmp_path: Path) -> None:
    truth, pred = _truth_and_prediction(scan_dir, tmp_path)
    script = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from semantic3d.cli.app import app\n"
        f"result = CliRunner().invoke(app, ['evaluate', '--gt', {str(truth)!r}, '--pred', {str(pred)!r}])\n"
        "assert result.exit_code == 0, result.output\n"
        "print(sorted(name for name in ('dask', 'distributed') if name in sys.modules))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    )
    assert done.stdout.strip() == "[]"


def test_train_on_a_running_scheduler_gives_the_same_model(
    cluster: DaskCluster, scan_dir: Path, tmp_path: Path
) -> None:
    from semantic3d.baselines.covariance.persistence import load_model
    from semantic3d.baselines.covariance.training import build_training_set, find_labelled_scans

    config = tmp_path / "tiny.toml"
    config.write_text(
        "[features]\nbase_voxel_size_m = 0.1\nn_levels = 5\n"
        "[forest]\nn_estimators = 4\nmax_depth = 10\n"
        "[sampling]\npoints_per_class = 150\n"
        "[prediction]\ntile_size_m = 4.8\n"
    )
    common = ["baseline", "covariance", "train", "--data", str(scan_dir), "--config", str(config)]
    common += ["--scans", "train,other"]
    plain = runner.invoke(app, [*common, "--out", str(tmp_path / "a.s3d")])
    address = cluster.client.scheduler.address
    remote = runner.invoke(
        app,
        [
            *common,
            "--out",
            str(tmp_path / "b.s3d"),
            "--scheduler",
            address,
            "--workdir",
            str(tmp_path / "w"),
        ],
    )
    assert plain.exit_code == remote.exit_code == 0, remote.output
    assert f"Dask: {address}" in remote.output and "trained on 2 scans" in remote.output
    single, distributed = load_model(tmp_path / "a.s3d"), load_model(tmp_path / "b.s3d")
    assert distributed.n_training_points == single.n_training_points
    scans = find_labelled_scans(scan_dir, names=["test"])
    rows = build_training_set(scans, config=single.config).features
    np.testing.assert_array_equal(
        distributed.classifier.predict_proba(rows), single.classifier.predict_proba(rows)
    )
    assert list((tmp_path / "w").iterdir()) == []
