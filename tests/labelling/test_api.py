"""The HTTP API the page uses, through FastAPI's TestClient."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from semantic3d.io import read_labels
from semantic3d.labelling.app import create_label_app
from semantic3d.labelling.session import open_label_session

from .conftest import NODE_CAPACITY

TOP_VIEW = np.diag([0.02, 0.02, -0.001, 1.0]).reshape(-1).tolist()
SQUARE = [(-0.2, -0.2), (0.2, -0.2), (0.2, 0.2), (-0.2, 0.2)]


@pytest.fixture
def client(simulated_scan, tmp_path):
    session = open_label_session(
        simulated_scan.cache.path, labels_path=tmp_path / "api.labels", node_capacity=NODE_CAPACITY
    )
    with TestClient(create_label_app(session)) as client:
        yield client
    session.close()


def test_nodes_and_both_workflows_over_http(client, simulated_scan, tmp_path) -> None:
    scan = client.get("/api/scan").json()
    nodes = scan["hierarchy"]["nodes"]
    n = simulated_scan.cache.n_points
    assert sum(node["count"] for node in nodes) == n == scan["summary"]["n_points"]
    assert [c["name"] for c in scan["classes"]][:2] == ["unlabelled", "man-made terrain"]
    root = nodes[0]
    body = client.get("/api/nodes/0").content
    assert len(body) == root["count"] * 16  # 12 bytes of float32 xyz, 3 of rgb, 1 of intensity
    positions = np.frombuffer(body, np.float32, 3 * root["count"]).reshape(-1, 3)
    low, high = np.array(root["bounds"][:3]), np.array(root["bounds"][3:])
    assert ((positions >= low - 1e-3) & (positions <= high + 1e-3)).all()
    state = client.get("/api/nodes/0/state").content
    assert len(state) == 3 * root["count"] and set(state[: root["count"]]) == {0}
    assert client.get(f"/api/nodes/{len(nodes)}").status_code == 404

    split = client.post("/api/split", json={"view_projection": TOP_VIEW, "polygon": SQUARE}).json()
    inside = split["result"]["n_working"]
    assert 0 < inside < n and split["summary"]["n_working"] == inside
    # 3D: fit the ground plane near the scanner, inside the square.
    sx, sy, sz = np.array(simulated_scan.station_m) - scan["hierarchy"]["origin"]
    seeds = [(sx + 2, sy, sz - 1.7), (sx - 1, sy + 2, sz - 1.7), (sx, sy - 2, sz - 1.7)]
    fit = client.post("/api/fit", json={"kind": "plane", "seeds": seeds, "tolerance_m": 0.15})
    assert fit.status_code == 200, fit.text
    result = fit.json()["result"]
    assert abs(result["model"]["normal"][2]) > 0.95 and 0 < result["n_inliers"] < inside
    assigned = client.post("/api/assign", json={"value": 2}).json()
    assert assigned["summary"]["layers"][2]["count"] == result["n_inliers"]
    client.post("/api/reset", json={"scope": "unlabelled"})
    client.post("/api/assign", json={"value": 5})
    undone = client.post("/api/undo").json()
    assert undone["summary"]["layers"][5]["count"] == 0 and undone["summary"]["can_redo"]
    saved = client.post("/api/save", json={}).json()
    labels = read_labels(saved["path"])
    assert (labels == 2).sum() == result["n_inliers"] and set(np.unique(labels)) == {0, 2}
    history = client.get("/api/history").json()
    assert [e["kind"] for e in history][-2:] == ["undo", "checkpoint"]


def test_bad_requests_are_explained(client, tmp_path) -> None:
    bad_matrix = client.post("/api/split", json={"view_projection": [1, 2], "polygon": SQUARE})
    assert bad_matrix.status_code == 422
    assert client.post("/api/undo").json()["detail"] == "nothing to undo"
    assert client.post("/api/assign", json={"value": 12}).status_code == 400
    client.post("/api/layers/3", json={"locked": True})
    locked = client.post("/api/assign", json={"value": 3})
    assert locked.status_code == 400 and "locked" in locked.json()["detail"]
    other = tmp_path / "other.labels"
    other.write_text("precious\n")
    refused = client.post("/api/save", json={"path": str(other)})
    assert refused.status_code == 409 and "already exists" in refused.json()["detail"]
    assert other.read_text() == "precious\n"
    forced = client.post("/api/save", json={"path": str(other), "overwrite": True})
    assert forced.status_code == 200 and other.read_text().startswith("0\n")


def test_the_viewer_is_read_only(simulated_scan) -> None:
    session = open_label_session(
        simulated_scan.cache.path,
        labels_path=simulated_scan.truth_path,
        prediction_path=simulated_scan.truth_path,
        read_only=True,
        node_capacity=NODE_CAPACITY,
    )
    with TestClient(create_label_app(session)) as client:
        summary = client.get("/api/summary").json()
        assert summary["read_only"] and summary["has_prediction"]
        assert summary["layers"][5]["count"] == (simulated_scan.truth == 5).sum()
        refused = client.post("/api/assign", json={"value": 1})
        assert refused.status_code == 403 and "read-only" in refused.json()["detail"]
        state = client.get("/api/nodes/0/state").content
        count = client.get("/api/scan").json()["hierarchy"]["nodes"][0]["count"]
        assert state[:count] == state[2 * count :]  # truth and prediction are the same file
