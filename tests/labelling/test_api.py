"""The HTTP API the page uses, through FastAPI's TestClient."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.io import read_labels
from semantic3d.labelling.app import create_label_app
from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.opening import open_label_session

from .conftest import NODE_CAPACITY, PORT, api_client

TOP_VIEW = np.diag([0.02, 0.02, -0.001, 1.0]).reshape(-1).tolist()
SQUARE = [(-0.2, -0.2), (0.2, -0.2), (0.2, 0.2), (-0.2, 0.2)]


@pytest.fixture
def client(simulated_scan, tmp_path):
    session = open_label_session(
        simulated_scan.cache.path, labels_path=tmp_path / "api.labels", node_capacity=NODE_CAPACITY
    )
    with api_client(create_label_app(session, port=PORT)) as client:
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
    with api_client(create_label_app(session, port=PORT)) as client:
        summary = client.get("/api/summary").json()
        assert summary["read_only"] and summary["has_prediction"]
        assert summary["layers"][5]["count"] == (simulated_scan.truth == 5).sum()
        refused = client.post("/api/assign", json={"value": 1})
        assert refused.status_code == 403 and "read-only" in refused.json()["detail"]
        state = client.get("/api/nodes/0/state").content
        count = client.get("/api/scan").json()["hierarchy"]["nodes"][0]["count"]
        assert state[:count] == state[2 * count :]  # truth and prediction are the same file


def _fresh_client(simulated_scan, tmp_path, **options):
    session = open_label_session(
        simulated_scan.cache.path,
        labels_path=tmp_path / "guarded.labels",
        node_capacity=NODE_CAPACITY,
        **options,
    )
    app = create_label_app(session, port=PORT)
    return session, app


def test_only_loopback_hosts_with_the_secret_reach_the_api(simulated_scan, tmp_path) -> None:
    from fastapi.testclient import TestClient

    session, app = _fresh_client(simulated_scan, tmp_path)
    secret = app.state.secret
    token = {"X-Semantic3D-Token": secret}
    try:
        for host in ("127.0.0.1", "localhost", "[::1]"):
            with TestClient(app, base_url=f"http://{host}:{PORT}") as client:
                assert client.get("/").status_code == 200  # the page needs no secret
                assert client.get("/api/summary", headers=token).status_code == 200
        with TestClient(app, base_url=f"http://127.0.0.1:{PORT}") as client:
            for headers in ({}, {"X-Semantic3D-Token": "x" * len(secret)}):
                refused = client.get("/api/summary", headers=headers)
                assert refused.status_code == 403 and "token" in refused.json()["detail"]
            assert client.get("/api/nodes/0").status_code == 403
            assert client.post("/api/undo").status_code == 403
            assert client.get("/api/summary?token=" + secret).status_code == 403  # header only
            page = client.get("/")
            assert page.headers["referrer-policy"] == "no-referrer"
            assert "frame-ancestors 'none'" in page.headers["content-security-policy"]
            # State changes only from the app's own origin.
            for origin in ("http://127.0.0.1:9999", "null", "http://evil.example"):
                crossed = client.post("/api/reset", json={}, headers={**token, "Origin": origin})
                assert crossed.status_code == 403 and "cross-origin" in crossed.json()["detail"]
            same = client.post(
                "/api/reset", json={}, headers={**token, "Origin": f"http://localhost:{PORT}"}
            )
            assert same.status_code == 200
            huge = client.post(
                "/api/reset",
                content=b" " * (2 << 20),
                headers={**token, "Content-Type": "application/json"},
            )
            assert huge.status_code == 413
        for host in (f"evil.example:{PORT}", "127.0.0.1:1", "127.0.0.1", f"127.0.0.2:{PORT}"):
            with TestClient(app, base_url=f"http://{host}") as client:
                rebound = client.get("/api/summary", headers=token)
                assert rebound.status_code == 421 and "unexpected Host" in rebound.json()["detail"]
                assert client.get("/").status_code == 421
        assert len(session.undo_stack) == 1  # only the same-origin reset ran
    finally:
        session.close()


def test_save_writes_only_labels_files_beside_the_labels_or_the_scan(
    simulated_scan, tmp_path
) -> None:
    session, app = _fresh_client(simulated_scan, tmp_path / "work")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    victim = tmp_path / "work" / "notes.txt"
    victim.write_text("keep me\n")
    try:
        with api_client(app) as client:
            for path, message in (
                (str(outside / "x.labels"), "expected a .labels file under"),
                ("../elsewhere/x.labels", "expected a .labels file under"),
                ("sub/../../elsewhere/x.labels", "expected a .labels file under"),
                (str(victim), "expected a file name ending in .labels"),
                ("notes.txt", "expected a file name ending in .labels"),
                (".hidden.labels", "expected a file name ending in .labels"),
                (str(simulated_scan.truth_path), "holds the labels of the scan"),
            ):
                refused = client.post("/api/save", json={"path": path, "overwrite": True})
                assert refused.status_code == 400, (path, refused.text)
                assert message in refused.json()["detail"], refused.json()
            link = tmp_path / "work" / "link.labels"
            link.symlink_to(outside / "target.labels")
            refused = client.post("/api/save", json={"path": "link.labels", "overwrite": True})
            assert refused.status_code == 400
            assert victim.read_text() == "keep me\n" and not list(outside.iterdir())
            assert client.post("/api/save", json={"path": "copy.labels"}).status_code == 200
            assert (tmp_path / "work" / "copy.labels").is_file()
            nested = client.post("/api/save", json={"path": "sub/deeper.labels"})
            assert nested.status_code == 400  # a missing folder is not created
            own = client.post("/api/save", json={}).json()["path"]
            assert own == str(tmp_path / "work" / "guarded.labels")
    finally:
        session.close()


def test_the_labels_a_session_reads_are_never_written(simulated_scan, tmp_path) -> None:
    prediction = tmp_path / "pred.labels"
    prediction.write_bytes(simulated_scan.truth_path.read_bytes())
    truth = tmp_path / "truth.labels"
    truth.write_bytes(simulated_scan.truth_path.read_bytes())
    session, app = _fresh_client(
        simulated_scan, tmp_path, start_from=truth, prediction_path=prediction
    )
    before = truth.read_bytes()
    try:
        with api_client(app) as client:
            for name in ("truth.labels", "pred.labels"):
                refused = client.post("/api/save", json={"path": name, "overwrite": True})
                assert refused.status_code == 400 and "what this session reads" in refused.text
            # The whole scan starts in the working set: assigning it asks first.
            unconfirmed = client.post("/api/assign", json={"value": 4})
            assert unconfirmed.status_code == 409 and unconfirmed.json()["confirm"] is True
            assert "whole scan" in unconfirmed.json()["detail"]
            confirmed = client.post("/api/assign", json={"value": 4, "confirm_whole_scan": True})
            assert confirmed.status_code == 200
            assert client.post("/api/save", json={}).status_code == 200
    finally:
        session.close()
    assert truth.read_bytes() == before and prediction.read_bytes() == before
    saved = read_labels(tmp_path / "guarded.labels")
    assert (saved == 4).all()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"radius_m": float("nan")}, "radius_m: input should be a finite number, found nan"),
        ({"radius_m": float("inf")}, "radius_m: input should be a finite number, found inf"),
        ({"radius_m": -1}, "radius_m: input should be greater than 0, found -1"),
        ({"radius_m": 1e9}, "radius_m: input should be less than or equal to 100000"),
        ({"tolerance_m": float("nan")}, "tolerance_m: input should be a finite number"),
        ({"tolerance_m": 0}, "tolerance_m: input should be greater than 0"),
        ({"seeds": [[0, 0, float("nan")]]}, "seeds.0.2: input should be a finite number"),
        ({"seeds": [[0.0, 0.0, 0.0]] * 5000}, "seeds: list should have at most 1000 items"),
        ({"seeds": []}, "seeds: list should have at least 1 item"),
        ({"kind": "torus"}, "kind: input should be 'plane', 'line', 'cylinder' or 'sphere'"),
    ],
)
def test_bad_fit_requests_get_one_clear_4xx(client, body, message) -> None:
    import json

    request = {"kind": "plane", "seeds": [[0.0, 0.0, 0.0]], "tolerance_m": 0.1, **body}
    answer = client.post(
        "/api/fit",
        content=json.dumps(request, allow_nan=True),
        headers={"Content-Type": "application/json"},
    )
    assert answer.status_code == 422, answer.text
    detail = answer.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail and len(detail) < 200
    assert detail.startswith(message), detail


def test_the_library_refuses_bad_fit_parameters_too(client) -> None:
    session = client.app.state.session
    for kwargs, message in (
        ({"radius_m": float("nan")}, "radius_m: expected a finite distance"),
        ({"radius_m": -2.0}, "radius_m: expected a finite distance"),
        ({"tolerance_m": float("inf")}, "tolerance_m: expected a finite distance"),
    ):
        options = {"tolerance_m": 0.1, **kwargs}
        with pytest.raises(OperationError, match=message):
            session.fit("plane", [[0.0, 0.0, 0.0]], **options)
    with pytest.raises(OperationError, match="seeds: expected finite coordinates"):
        session.fit("plane", [[0.0, float("nan"), 0.0]], tolerance_m=0.1)


def test_preview_commit_progress_cancel_and_stats_over_http(client, simulated_scan) -> None:
    origin = np.array(client.get("/api/scan").json()["hierarchy"]["origin"])
    sx, sy, sz = np.array(simulated_scan.station_m) - origin
    seeds = [(sx + 2, sy, sz - 1.7), (sx - 1, sy + 2, sz - 1.7), (sx, sy - 2, sz - 1.7)]
    region = {"kind": "sphere", "centre": [sx, sy, sz - 1.7], "radius_m": 6.0}
    body = {"kind": "plane", "seeds": seeds, "tolerance_m": 0.15, "region": region}
    preview = client.post("/api/fit/preview", json=body)
    assert preview.status_code == 200, preview.text
    shown = preview.json()
    assert shown["n_inliers"] > 100 and len(shown["sample"]) == min(shown["n_inliers"], 30_000)
    assert client.get("/api/summary").json()["can_undo"] is False
    committed = client.post("/api/fit", json={**body, "model": shown["model"]}).json()
    assert committed["result"]["n_inliers"] == shown["n_inliers"]
    assert committed["result"]["model"] == shown["model"]
    bad_region = client.post(
        "/api/fit/preview",
        json={**body, "region": {"kind": "box", "min": [0, 0, 0], "max": [0, 1, 1]}},
    )
    assert bad_region.status_code == 400 and "min < max" in bad_region.json()["detail"]
    idle = client.get("/api/progress").json()
    assert idle["running"] is False and client.post("/api/cancel").json() == {"cancelled": False}
    stats = client.post("/api/stats", json={"scope": "working"}).json()
    assert stats["n_points"] == shown["n_inliers"] and stats["has_prediction"] is False
    view = client.post("/api/stats", json={"scope": "view", "view_projection": TOP_VIEW}).json()
    assert 0 < view["n_points"] <= simulated_scan.cache.n_points
