"""Both workflows driven in a real headless Chromium (Debian's, WebGL through SwiftShader).

Open a simulated scan, split it with a polygon drawn in the fixed top view, fit the ground
plane through three picked points, assign classes, undo with the keyboard, save, and check
the written ``.labels``. Screenshots are kept in the test's temporary folder (or under
``$SEMANTIC3D_TEST_ARTIFACTS``). Never downloads a browser: skips without /usr/bin/chromium.
"""

from __future__ import annotations

import os
import re
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import semantic3d.labelling
from semantic3d.io import read_labels
from semantic3d.labelling.opening import open_label_session
from semantic3d.labelling.session import LabelSession
from tests.browsers import SOFTWARE_WEBGL_ARGS, chromium

from .conftest import NODE_CAPACITY

pytestmark = pytest.mark.slow

HALF_SQUARE_M = 12.0


REBOUND_HOST = "rebound.test"


@pytest.fixture(scope="module")
def browser():
    # A host name that resolves to 127.0.0.1, as a DNS-rebinding attacker's would.
    rules = f"--host-resolver-rules=MAP {REBOUND_HOST} 127.0.0.1"
    with chromium((*SOFTWARE_WEBGL_ARGS, rules)) as browser:
        yield browser


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class _Server:
    """The app served by uvicorn in a thread of this process, on a free port."""

    def __init__(self, session: LabelSession, *, record: list | None = None) -> None:
        import uvicorn

        from semantic3d.labelling.app import create_label_app

        port = _free_port()
        app = create_label_app(session, port=port)
        self.port = port
        self.secret = app.state.secret
        served = app
        if record is not None:

            async def served(scope, receive, send):  # type: ignore[no-untyped-def]
                async def spy(message):  # type: ignore[no-untyped-def]
                    if message["type"] == "http.response.start":
                        record.append((scope["method"], scope["path"], message["status"]))
                    await send(message)

                await app(scope, receive, spy)

        config = uvicorn.Config(served, host="127.0.0.1", port=port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            if time.monotonic() > deadline:
                raise RuntimeError("the labelling server did not start")
            time.sleep(0.05)
        self.base = f"http://127.0.0.1:{port}"
        self.url = f"{self.base}/?token={self.secret}"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)


@pytest.fixture
def served(simulated_scan, tmp_path) -> Iterator[tuple[_Server, LabelSession, Path]]:
    labels_path = tmp_path / "browser.labels"
    session = open_label_session(
        simulated_scan.cache.path, labels_path=labels_path, node_capacity=NODE_CAPACITY
    )
    server = _Server(session)
    try:
        yield server, session, labels_path
    finally:
        server.stop()
        session.close()


def _idle(page) -> None:
    page.wait_for_function(
        "() => { const s = document.getElementById('status');"
        " return s.dataset.idle === 'true' && !s.textContent.startsWith('0 '); }",
        timeout=30_000,
    )
    page.wait_for_timeout(150)  # one more animation frame after the last node


APP_JS = Path(semantic3d.labelling.__file__).parent / "static" / "app.js"
_KEY_NAMES = {"enter": "Enter", "backspace": "Backspace", "escape": "Escape"}


def _keys_handled() -> tuple[set[str], set[str]]:
    """The keys the page's keydown handler acts on, named as a user reads them, and of
    those the ones it ignores in the read-only viewer (every Ctrl key, ``EDIT_KEYS``)."""
    source = APP_JS.read_text()
    handler = source[source.index("  key(e) {") : source.index("  toggleHelp()")]
    skipped = re.search(r"const EDIT_KEYS = new Set\(\[(.*?)\]\)", source)
    assert skipped is not None
    editing = {_KEY_NAMES.get(k, k.upper()) for k in re.findall(r"'(.+?)'", skipped.group(1))}
    handled: set[str] = set()
    for line in handler.splitlines():
        for key in re.findall(r"key === '(.+?)'", line):
            name = _KEY_NAMES.get(key, key.upper())
            if "ctrl && key" in line:
                names = {f"Ctrl+{name}"} | (
                    {f"Ctrl+Shift+{name}"} if "e.shiftKey" in line else set()
                )
                handled |= names
                editing |= names
            else:
                handled.add(name)
    assert {"Ctrl+Z", "Backspace", "Enter", "D", "V", "H", "?"} <= handled, handled  # parsed
    return handled, editing


def _help_keys(page) -> set[str]:
    """The keys the help panel lists (its first column, comma-separated)."""
    cells = page.eval_on_selector_all(
        "#help-keys tr td:first-child", "cells => cells.map((c) => c.textContent)"
    )
    return {key.strip() for cell in cells for key in cell.split(",")}


def _client(page, xyz) -> tuple[float, float]:
    x, y = page.evaluate("p => window.labelApp.viewer.toClient(p[0], p[1], p[2])", list(xyz))
    return x, y


def test_polygon_split_plane_fit_assign_undo_save(browser, served, simulated_scan, tmp_path):
    server, session, labels_path = served
    artifacts = Path(os.environ.get("SEMANTIC3D_TEST_ARTIFACTS", tmp_path))
    artifacts.mkdir(parents=True, exist_ok=True)
    # bypass_csp: Playwright's wait_for_function evaluates strings, which the page's CSP
    # forbids; the page itself loads under its CSP in the test of other origins below.
    page = browser.new_page(viewport={"width": 1200, "height": 800}, bypass_csp=True)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    try:
        page.goto(server.url)
        _idle(page)
        assert "token" not in page.url  # the secret left the address bar
        page.screenshot(path=str(artifacts / "labelling-1-opened.png"))
        n = session.n_points
        assert page.inner_text("#working-count") == f"{n:,}"

        # 2D workflow: fixed top view, a square around the scanner, keep the inside.
        page.click("#view-top")
        _idle(page)
        origin = session.origin
        station = np.array(simulated_scan.station_m) - origin
        h = HALF_SQUARE_M
        corners = [
            station + np.array((dx, dy, 0.0)) for dx, dy in ((-h, -h), (h, -h), (h, h), (-h, h))
        ]
        page.click("#draw-polygon")
        for corner in corners:
            page.mouse.click(*_client(page, corner))
        page.click("#finish-polygon")
        page.screenshot(path=str(artifacts / "labelling-2-polygon.png"))
        page.click("#keep-inside")
        page.wait_for_function(f"document.getElementById('working-count').textContent !== '{n:,}'")
        _idle(page)
        xy = np.asarray(simulated_scan.cache.xyz)[:, :2] - origin[:2] - station[:2]
        offset = np.abs(xy).max(axis=1)
        working = session.working
        assert 0 < working.sum() < n
        assert (offset[working] < h + 1.0).all()  # the polygon's edges are pixel-snapped
        assert working[offset < h - 1.0].all()

        # 3D workflow: frame the working set, pick three ground points, fit a plane.
        page.click("#frame-working")
        _idle(page)
        page.click("#pick-points")
        ground = station - (0.0, 0.0, simulated_scan.station_m[2])  # the tripod stands on it
        for dx, dy in ((4.0, 0.5), (-3.0, 3.5), (0.5, -4.0)):
            page.mouse.click(*_client(page, ground + np.array((dx, dy, 0.0))))
        assert page.inner_text("#pick-count") == "3 picked"
        page.select_option("#model-kind", "plane")
        before_fit = int(session.working.sum())
        page.click("#fit-model")
        page.wait_for_function(
            "document.getElementById('fit-result').textContent.includes('inliers')"
        )
        _idle(page)
        page.screenshot(path=str(artifacts / "labelling-3-plane-fit.png"))
        inliers = int(session.working.sum())
        assert 0 < inliers < before_fit
        model = session.journal.operations()[-1]["operation"]["model"]
        assert model["kind"] == "plane" and abs(model["normal"][2]) > 0.95

        # Assign the inliers to natural terrain, the rest of the scan to buildings, undo that.
        page.select_option("#assign-class", "2")
        page.click("#assign")
        page.wait_for_function(
            "document.querySelector('#layers tr[data-value=\"2\"] td.count').textContent !== '0'"
        )
        page.click("#reset-unlabelled")
        page.wait_for_function(
            f"document.getElementById('working-count').textContent === '{n - inliers:,}'"
        )
        page.select_option("#assign-class", "5")
        page.click("#assign")
        page.wait_for_function(
            "document.querySelector('#layers tr[data-value=\"0\"] td.count').textContent === '0'"
        )
        _idle(page)
        page.keyboard.press("Control+z")
        page.wait_for_function(
            "document.querySelector('#layers tr[data-value=\"5\"] td.count').textContent === '0'"
        )
        page.select_option("#colour-mode", "class")
        _idle(page)
        page.screenshot(path=str(artifacts / "labelling-4-assigned.png"))
        page.click("#save")
        page.wait_for_function(
            "document.getElementById('save-status').textContent.startsWith('saved')"
        )
    finally:
        page.close()
    labels = read_labels(labels_path)
    assert labels.size == n
    assert (labels == 2).sum() == inliers and set(np.unique(labels)) == {0, 2}
    on_plane = labels == 2
    assert (offset[on_plane] < h + 1.0).all()
    heights = np.asarray(simulated_scan.cache.xyz)[on_plane, 2]
    assert np.ptp(heights) < 3.0  # a ground plane, not the walls
    assert (simulated_scan.truth[on_plane] == 5).sum() < 0.05 * on_plane.sum()
    assert not errors, errors
    assert (artifacts / "labelling-4-assigned.png").stat().st_size > 5_000


VIEWER_CONTROLS = {
    "help-toggle", "colour-mode", "point-size", "point-budget",
    "view-free", "view-top", "view-front", "view-side", "view-free2d", "frame-dense",
    "measure", "clear-measure", "stats-working", "stats-view",
    "show-layer",  # one per class
}  # fmt: skip
"""The viewer's visible controls (the colour range fields appear with height and intensity)."""


def _visible_controls(page) -> set[str]:
    """Ids (or, without one, class names) of the buttons, fields and lists on show."""
    return set(
        page.eval_on_selector_all(
            "button, input, select, textarea",
            "all => all.filter((e) => e.getClientRects().length).map((e) => e.id || e.className)",
        )
    )


def test_the_viewer_shows_prediction_errors_read_only(browser, simulated_scan, tmp_path):
    from PIL import Image

    from semantic3d.io import write_labels

    truth = simulated_scan.truth
    prediction = truth.copy()
    wrong = np.random.default_rng(0).random(truth.size) < 0.3
    prediction[wrong] = (prediction[wrong] % 8) + 1
    pred_path = tmp_path / "pred.labels"
    write_labels(pred_path, [prediction])
    session = open_label_session(
        simulated_scan.cache.path,
        labels_path=simulated_scan.truth_path,
        prediction_path=pred_path,
        read_only=True,
        node_capacity=NODE_CAPACITY,
    )
    server = _Server(session)
    artifacts = Path(os.environ.get("SEMANTIC3D_TEST_ARTIFACTS", tmp_path))
    page = browser.new_page(viewport={"width": 1000, "height": 700}, bypass_csp=True)
    try:
        page.goto(server.url)
        _idle(page)
        assert page.inner_text("#mode-line") == "read-only viewer"
        # Only viewing controls are shown: no selection, fit, layer edit, history or save.
        assert _visible_controls(page) == VIEWER_CONTROLS
        assert page.locator("#layers th:visible").all_inner_texts() == [
            "",
            "class",
            "points",
            "show",
        ]
        page.keyboard.press("h")
        handled, editing = _keys_handled()
        assert _help_keys(page) == handled - editing  # the keys the viewer acts on, no others
        page.keyboard.press("Escape")
        for key in ("d", "p", "Backspace", "Control+z"):  # editing keys do nothing here
            page.keyboard.press(key)
        assert page.evaluate(
            "window.labelApp.tool.kind === null && window.labelApp.mode === 'orbit'"
        )
        page.click("#stats-working")
        page.wait_for_function("document.getElementById('stats').textContent.includes('confusion')")
        assert "overall accuracy" in page.inner_text("#stats")
        assert f"scan: {session.n_points:,} points" in page.inner_text("#stats")
        page.click("#view-top")
        page.select_option("#colour-mode", "prediction")
        assert "buildings" in page.inner_text("#legend") and "no prediction" in page.inner_text(
            "#legend"
        )
        page.select_option("#colour-mode", "errors")
        legend = page.inner_text("#legend")
        assert "right" in legend and "wrong" in legend and "unlabelled truth" in legend
        page.evaluate(
            "() => { const s = document.getElementById('point-size');"
            " s.value = '4'; s.dispatchEvent(new Event('input')); }"
        )
        _idle(page)
        shot = artifacts / "viewer-errors.png"
        page.locator("#stage").screenshot(path=str(shot))
    finally:
        page.close()
        server.stop()
        session.close()
    pixels = np.asarray(Image.open(shot).convert("RGB")).reshape(-1, 3).astype(int)
    red = ((pixels[:, 0] > 180) & (pixels[:, 1] < 80) & (pixels[:, 2] < 80)).sum()
    green = ((pixels[:, 1] > 140) & (pixels[:, 0] < 90) & (pixels[:, 2] < 110)).sum()
    assert red > 50 and green > 50 and green > red  # 70 % right, 30 % wrong


_ATTACK = """
async (target) => {
  const outcomes = [];
  for (let i = 0; i < 10; i++) {
    try { await fetch(`${target}/api/undo`, { method: 'POST', mode: 'no-cors' }); outcomes.push('sent'); }
    catch (e) { outcomes.push('blocked'); }
  }
  try {
    await fetch(`${target}/api/assign`, {
      method: 'POST', body: JSON.stringify({ value: 1, confirm_whole_scan: true }),
      headers: { 'Content-Type': 'application/json', 'X-Semantic3D-Token': 'guess' },
    });
    outcomes.push('cors-sent');
  } catch (e) { outcomes.push('cors-blocked'); }
  navigator.sendBeacon(`${target}/api/reset`, '{}');
  const form = document.createElement('form');
  form.method = 'POST'; form.action = `${target}/api/redo`; form.target = 'sink';
  const sink = document.createElement('iframe'); sink.name = 'sink';
  document.body.append(sink, form);
  form.submit();
  await new Promise((resolve) => setTimeout(resolve, 500));
  return outcomes;
}
"""


def test_pages_of_other_origins_cannot_drive_the_app(browser, simulated_scan, tmp_path):
    """No-cors POSTs, beacons, form posts and a DNS-rebinding host are all refused."""
    import http.server

    session = open_label_session(
        simulated_scan.cache.path,
        labels_path=tmp_path / "target.labels",
        node_capacity=NODE_CAPACITY,
    )
    session.split(np.diag([0.02, 0.02, -0.001, 1.0]), [(-0.2, -0.2), (0.2, -0.2), (0.2, 0.2)])
    session.assign(6)
    before = (session.labels.copy(), list(session.undo_stack))
    record: list[tuple[str, str, int]] = []
    server = _Server(session, record=record)

    class Attacker(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = b"<!doctype html><title>elsewhere</title><p>hello</p>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    attacker = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Attacker)
    threading.Thread(target=attacker.serve_forever, daemon=True).start()
    page = browser.new_page()
    try:
        page.goto(f"http://127.0.0.1:{attacker.server_address[1]}/")
        outcomes = page.evaluate(_ATTACK, server.base)
        assert outcomes.count("sent") == 10 and outcomes[-1] == "cors-blocked"
        page.wait_for_timeout(300)
        # DNS rebinding: the attacker's name now points at the app; the app ignores it.
        rebound = page.goto(f"http://{REBOUND_HOST}:{server.port}/")
        assert rebound is not None and rebound.status == 421
        rebound_api = page.evaluate(
            "async (u) => (await fetch(u, {method: 'POST'})).status",
            f"http://{REBOUND_HOST}:{server.port}/api/undo",
        )
        assert rebound_api == 421
        # The app's own page, under its Content-Security-Policy, works with the secret.
        console: list[str] = []
        page.on("console", lambda message: console.append(message.text))
        page.goto(server.url)
        for _ in range(100):
            if page.evaluate("document.getElementById('status').dataset.idle === 'true'"):
                break
            page.wait_for_timeout(100)
        assert page.evaluate("document.getElementById('error').textContent") == ""
        assert not [line for line in console if "Content Security Policy" in line], console
        assert "token" not in page.url
        page.reload()  # the secret stays with the tab, not in the address
        name = ""
        for _ in range(100):
            name = page.evaluate("document.getElementById('scan-name').textContent")
            if name != "semantic3d":
                break
            page.wait_for_timeout(100)
        assert name == simulated_scan.cache.path.name
    finally:
        page.close()
        attacker.shutdown()
        server.stop()
        session.close()
    posts = [(path, status) for method, path, status in record if method == "POST"]
    assert ("/api/undo", 403) in posts and ("/api/reset", 403) in posts  # they did arrive
    assert ("/api/redo", 403) in posts
    assert all(status in (403, 421) for _, status in posts), posts
    np.testing.assert_array_equal(session.labels, before[0])
    assert session.undo_stack == before[1] and session.redo_stack == []


def _offset(base: np.ndarray, dx: float, dy: float, dz: float) -> np.ndarray:
    return base + np.array([dx, dy, dz])


def test_interactions_of_a_surveyor(browser, served, simulated_scan, tmp_path):
    """Double-click, Backspace, lasso, brush, measure, legends, preview, remembered view, help."""
    server, session, _ = served
    page = browser.new_page(viewport={"width": 1200, "height": 800}, bypass_csp=True)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("dialog", lambda dialog: dialog.accept())
    try:
        page.goto(server.url)
        _idle(page)
        origin = session.origin
        station = np.array(simulated_scan.station_m) - origin
        n = session.n_points

        # Help lists every key the page handles.
        page.keyboard.press("h")
        assert page.is_visible("#help")
        handled, _ = _keys_handled()
        assert _help_keys(page) == handled | {"double-click"}
        page.keyboard.press("Escape")
        assert not page.is_visible("#help")

        # Legends for every colour mode; a height range the user sets.
        for mode, expected in (
            ("class", "buildings"),
            ("rgb", "as scanned"),
            ("intensity", "intensity"),
            ("height", "height"),
        ):
            page.select_option("#colour-mode", mode)
            assert expected in page.inner_text("#legend")
        page.fill("#range-low", f"{origin[2] - 1:.2f}")
        page.fill("#range-high", f"{origin[2] + 3:.2f}")
        page.dispatch_event("#range-high", "change")
        assert f"{origin[2] + 3:.2f}" in page.inner_text("#legend")
        page.select_option("#colour-mode", "class")
        page.evaluate("document.activeElement.blur()")

        # Polygon: Backspace removes a vertex, a double click closes it.
        page.keyboard.press("t")
        _idle(page)
        assert page.evaluate("window.labelApp.viewer.view") == "top"
        page.keyboard.press("d")
        h = HALF_SQUARE_M
        corners = [_offset(station, dx, dy, 0.0) for dx, dy in ((-h, -h), (h, -h), (h, h), (-h, h))]
        for corner in corners[:3]:
            page.mouse.click(*_client(page, corner))
        page.mouse.click(*_client(page, _offset(station, 0.0, -1.4 * h, 0.0)))  # a wrong vertex
        page.keyboard.press("Backspace")
        assert page.evaluate("window.labelApp.tool.polygon.length") == 3
        page.mouse.dblclick(*_client(page, corners[3]))
        assert page.evaluate("window.labelApp.tool.closed")
        assert page.evaluate("window.labelApp.tool.polygon.length") == 4
        page.click("#keep-inside")
        page.wait_for_function(f"document.getElementById('working-count').textContent !== '{n:,}'")
        _idle(page)
        after_polygon = int(session.working.sum())
        assert 0 < after_polygon < n

        # Lasso: drag around the station's neighbourhood, keep what is inside.
        page.keyboard.press("l")
        ring = [
            _offset(station, 6 * np.cos(a), 6 * np.sin(a), 0.0)
            for a in np.linspace(0, 2 * np.pi, 24)
        ]
        page.mouse.move(*_client(page, ring[0]))
        page.mouse.down()
        for point in ring[1:]:
            page.mouse.move(*_client(page, point))
        page.mouse.up()
        page.click("#keep-inside")
        page.wait_for_function(
            f"document.getElementById('working-count').textContent !== '{after_polygon:,}'"
        )
        _idle(page)
        xy = np.asarray(simulated_scan.cache.xyz)[:, :2] - origin[:2] - station[:2]
        radius = np.hypot(xy[:, 0], xy[:, 1])
        working = session.working.copy()
        assert 0 < working.sum() < after_polygon
        assert (radius[working] < 6.5).all() and working[radius < 5.0].mean() > 0.95

        # Brush: a stroke across the middle, keep what is outside it.
        page.keyboard.press("b")
        page.mouse.move(*_client(page, _offset(station, -7.0, 0.0, 0.0)))
        page.mouse.down()
        page.mouse.move(*_client(page, _offset(station, 7.0, 0.0, 0.0)), steps=8)
        page.mouse.up()
        page.click("#keep-outside")
        page.wait_for_function(
            f"document.getElementById('working-count').textContent !== '{int(working.sum()):,}'"
        )
        _idle(page)
        assert 0 < session.working.sum() < working.sum()
        assert session.journal.operations()[-1]["operation"]["name"] == "split_mask"

        # Measure two points: georeferenced coordinates, distance and height between them.
        page.click("#frame-working")
        _idle(page)
        page.keyboard.press("m")
        ground = station - (0.0, 0.0, simulated_scan.station_m[2])
        local = np.asarray(simulated_scan.cache.xyz) - origin
        near = np.flatnonzero(
            (np.abs(local[:, 2] - ground[2]) < 0.3) & (np.abs(radius - 4.0) < 0.5) & session.working
        )
        a = local[near[0]]
        b = local[near[np.argmax(np.linalg.norm(local[near] - a, axis=1))]]
        for point in (a, b):
            page.mouse.click(*_client(page, point))
        text = page.inner_text("#measure-result")
        assert text.count("#") >= 3 and "distance" in text and "height" in text, text
        first_x = float(text.split("x ")[1].split()[0])
        assert abs(first_x - (origin[0] + a[0])) < 0.05  # the scan's own frame
        distance = float(text.split("distance ")[1].split()[0])
        assert abs(distance - np.linalg.norm(b - a)) < 0.1
        page.keyboard.press("Escape")

        # Fit with a preview: picks, a sphere region shown, then keep the previewed inliers.
        page.click("#reset-all")
        _idle(page)
        page.keyboard.press("p")
        for dx, dy in ((3.0, 0.5), (-2.0, 2.5), (0.5, -3.0)):
            page.mouse.click(*_client(page, _offset(ground, dx, dy, 0.0)))
        page.click("#fit-preview")
        page.wait_for_function(
            "document.getElementById('fit-result').textContent.startsWith('preview')"
        )
        shown = int(page.inner_text("#fit-result").split(", ")[1].split()[0].replace(",", ""))
        assert page.evaluate("window.labelApp.viewer.regionObject !== null")
        page.click("#fit-model")
        page.wait_for_function(
            "!document.getElementById('fit-result').textContent.startsWith('preview')"
        )
        _idle(page)
        assert int(session.working.sum()) == shown
        assert session.journal.operations()[-1]["operation"]["region"]["kind"] == "sphere"

        # The view, colour mode and budget come back after a reload.
        page.keyboard.press("v")  # a free 2D view along the current direction
        page.select_option("#colour-mode", "height")
        page.select_option("#point-budget", "500000")
        _idle(page)
        before = page.evaluate("window.labelApp.viewer.viewState()")
        assert before["view"] == "free2d"
        page.reload()
        _idle(page)
        after = page.evaluate("window.labelApp.viewer.viewState()")
        assert after["view"] == "free2d"
        np.testing.assert_allclose(after["position"], before["position"], atol=1e-3)
        assert page.input_value("#colour-mode") == "height"
        assert page.input_value("#point-budget") == "500000"
        assert page.is_visible("#scale-bar") and "m" in page.inner_text("#scale-text")
    finally:
        page.close()
    assert not errors, errors


_CURSOR_RAY_POINT = """([x, y]) => {
  const v = window.labelApp.viewer, camera = v.camera, Vector3 = camera.position.constructor;
  const [u, w] = v.ndcOf(x, y);
  camera.updateMatrixWorld();
  const near = new Vector3(u, w, -1).unproject(camera).toArray();
  const far = new Vector3(u, w, 1).unproject(camera).toArray();
  const direction = far.map((f, k) => f - near[k]);
  const length = Math.hypot(...direction);
  const depth = camera.position.distanceTo(v.controls.target);
  return near.map((n, k) => n + (direction[k] / length) * depth);
}"""


def test_start_view_zoom_to_cursor_and_2d_along_the_view(browser, served, simulated_scan):
    """The start view frames the dense part; the wheel zooms to the cursor; 2D here looks
    along the current direction at the same scale; 2D views show a true scale bar and axes."""
    server, session, _ = served
    page = browser.new_page(viewport={"width": 1200, "height": 800}, bypass_csp=True)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    try:
        page.goto(server.url)
        _idle(page)
        # Far returns make the bounds ten times the dense part: the start view ignores them.
        local = np.asarray(simulated_scan.cache.xyz) - session.origin
        low, high = np.percentile(local, [5, 95], axis=0)
        start = page.evaluate(
            """() => { const v = window.labelApp.viewer;
              return { low: v.frame.min.toArray(), high: v.frame.max.toArray(),
                       target: v.controls.target.toArray(), camera: v.camera.position.toArray(),
                       bounds: v.bounds.max.clone().sub(v.bounds.min).toArray() }; }"""
        )
        size = max(np.subtract(start["high"], start["low"]))
        assert max(start["bounds"]) > 5 * max(high - low)  # the simulated scan has far returns
        np.testing.assert_allclose(start["low"], low, atol=0.1 * max(high - low))
        np.testing.assert_allclose(start["high"], high, atol=0.1 * max(high - low))
        np.testing.assert_allclose(start["target"], (low + high) / 2, atol=0.1 * max(high - low))
        distance = np.linalg.norm(np.subtract(start["camera"], start["target"]))
        assert distance == pytest.approx(1.1 * size, rel=1e-3)

        # Zoom to the cursor, in orbit and in a 2D view: the point under it stays under it.
        box = page.locator("#stage").bounding_box()
        assert box is not None
        for view in ("o", "t"):
            page.keyboard.press(view)
            _idle(page)
            cursor = (box["x"] + 0.25 * box["width"], box["y"] + 0.3 * box["height"])
            under = page.evaluate(_CURSOR_RAY_POINT, list(cursor))
            before = page.evaluate("window.labelApp.viewer.metresPerPixel()")
            page.mouse.move(*cursor)
            page.mouse.wheel(0, -400)
            _idle(page)
            assert page.evaluate("window.labelApp.viewer.metresPerPixel()") < 0.9 * before, view
            np.testing.assert_allclose(_client(page, under), cursor, atol=2.0, err_msg=view)

        # 2D here from an oblique orbit view: the same direction and scale, rotation off.
        page.keyboard.press("o")
        _idle(page)
        oblique = page.evaluate(
            """() => { const v = window.labelApp.viewer, t = v.controls.target;
              v.camera.position.set(t.x + 30, t.y - 12, t.z + 9); v.controls.update();
              return { direction: t.clone().sub(v.camera.position).normalize().toArray(),
                       metresPerPixel: v.metresPerPixel() }; }"""
        )
        page.keyboard.press("v")
        _idle(page)
        flat = page.evaluate(
            """() => { const v = window.labelApp.viewer, c = v.camera;
              return { view: v.view, orthographic: c.isOrthographicCamera,
                       rotate: v.controls.enableRotate, metresPerPixel: v.metresPerPixel(),
                       direction: c.getWorldDirection(c.position.clone()).toArray() }; }"""
        )
        assert flat["view"] == "free2d" and flat["orthographic"] and not flat["rotate"]
        np.testing.assert_allclose(flat["direction"], oblique["direction"], atol=1e-6)
        assert flat["metresPerPixel"] == pytest.approx(oblique["metresPerPixel"], rel=1e-3)
        right, up = page.evaluate("window.labelApp.viewer.screenAxes()").values()
        assert abs(right[2]) < 1e-6 and up[2] > 0  # a street's facade stands upright
        page.keyboard.press("t")
        _idle(page)
        top = page.evaluate("window.labelApp.viewer.metresPerPixel()")
        page.keyboard.press("v")  # from a 2D view: along it, at its scale
        _idle(page)
        flat = page.evaluate(
            "(() => { const c = window.labelApp.viewer.camera;"
            " return c.getWorldDirection(c.position.clone()).toArray(); })()"
        )
        np.testing.assert_allclose(flat, [0.0, 0.0, -1.0], atol=1e-6)
        assert page.evaluate("window.labelApp.viewer.metresPerPixel()") == pytest.approx(top)

        # The scale bar says what its pixels measure; the axes name the screen's directions.
        for view in ("v", "t"):
            page.keyboard.press(view)
            _idle(page)
            width_px = page.evaluate(
                "parseFloat(document.getElementById('scale-line').style.width)"
            )
            number, unit = page.inner_text("#scale-text").split()
            length_m = float(number) * (1e-3 if unit == "mm" else 1.0)
            metres_per_pixel = page.evaluate("window.labelApp.viewer.metresPerPixel()")
            assert width_px * metres_per_pixel == pytest.approx(length_m, rel=1e-3)
            assert 40 <= width_px <= 120
        assert page.inner_text("#axes").split("\n") == ["→ +x", "↑ +y"]
        page.keyboard.press("o")
        assert not page.is_visible("#scale-bar") and not page.is_visible("#axes")
    finally:
        page.close()
    assert not errors, errors


def test_a_long_operation_shows_its_progress_and_the_page_cancels_it(
    browser, served, simulated_scan, monkeypatch
):
    """A split held on the server shows a progress bar; its cancel button leaves nothing."""
    server, session, _ = served
    asked = threading.Event()
    cancel, update = session.progress.cancel, session.progress.update

    def cancel_and_tell() -> bool:
        cancelled = cancel()
        asked.set()
        return cancelled

    def held(done: int) -> None:  # the split lingers after its first node until cancelled
        update(done)
        if done > 0:
            asked.wait(20)
            update(done)

    monkeypatch.setattr(session.progress, "cancel", cancel_and_tell)
    monkeypatch.setattr(session.progress, "update", held)
    page = browser.new_page(viewport={"width": 1200, "height": 800}, bypass_csp=True)
    try:
        page.goto(server.url)
        _idle(page)
        entries = len(session.journal.operations())
        station = np.array(simulated_scan.station_m) - session.origin
        page.keyboard.press("t")
        _idle(page)
        page.keyboard.press("d")
        h = HALF_SQUARE_M
        for dx, dy in ((-h, -h), (h, -h), (h, h), (-h, h)):
            page.mouse.click(*_client(page, _offset(station, dx, dy, 0.0)))
        page.keyboard.press("Enter")
        page.click("#keep-inside")
        page.wait_for_selector("#progress", state="visible", timeout=10_000)
        page.wait_for_function(
            "document.getElementById('progress-text').textContent.startsWith('split: ')"
        )
        assert not asked.is_set()
        page.click("#cancel-operation")
        page.wait_for_function("document.getElementById('error').textContent.includes('cancelled')")
        assert page.is_hidden("#progress")
        assert page.inner_text("#working-count") == f"{session.n_points:,}"
    finally:
        page.close()
    assert asked.is_set() and session.working.all()
    assert len(session.journal.operations()) == entries


def test_a_long_tour_stays_under_the_memory_budget(browser, served):
    """Nodes are evicted (least recently shown first) to keep the loaded points bounded."""
    server, session, _ = served
    page = browser.new_page(viewport={"width": 900, "height": 600}, bypass_csp=True)
    try:
        page.goto(server.url)
        _idle(page)
        page.evaluate(
            "() => { const v = window.labelApp.viewer; v.setBudget(6000); v.memoryBudget = 9000; }"
        )
        largest = max(node.count for node in session.lod.nodes)
        peaks: list[int] = []
        trace: list[dict] = []
        for step in range(12):
            page.evaluate(
                """async (k) => { const v = window.labelApp.viewer, f = v.frame;
                  const c = f.getCenter(v.centre.clone()), size = f.max.x - f.min.x;
                  const a = k * 0.9, r = size * (0.03 + 0.03 * (k % 4));
                  v.controls.target.set(c.x + 0.35 * size * Math.cos(a), c.y + 0.35 * size * Math.sin(a), c.z);
                  const t = v.controls.target;
                  v.camera.position.set(t.x + r, t.y - r, t.z + r * 0.5);
                  v.controls.update(); v.settleNow();
                  return new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done))); }""",
                step,
            )
            _idle(page)
            peaks.append(page.evaluate("window.labelApp.viewer.stats().loadedPoints"))
            trace.append(page.evaluate("window.labelApp.viewer.stats()"))
        evicted = page.evaluate("window.labelApp.viewer.stats().evicted")
    finally:
        page.close()
    assert evicted > 0, (peaks, largest, trace)
    assert max(peaks) <= 9000 + 2 * largest, (peaks, largest)


_RECORD_DRAWS = """() => {
  const v = window.labelApp.viewer, draw = v.draw.bind(v);
  window.draws = [];
  v.draw = (nodes, target, clear = true) => {
    const points = nodes.reduce((sum, node) => sum + node.info.count, 0);
    window.draws.push({ points, screen: !target, clear, limit: v.framePoints });
    draw(nodes, target, clear);
  };
  v.framePoints = 7000;
}"""


def test_frames_draw_bounded_slices_and_a_press_stops_the_refinement(browser, served):
    """A move draws one slice a frame, straight to the screen; at rest slices add up."""
    server, session, _ = served
    largest = max(node.count for node in session.lod.nodes)
    page = browser.new_page(viewport={"width": 900, "height": 600}, bypass_csp=True)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    try:
        page.goto(server.url)
        _idle(page)
        full = page.evaluate("window.labelApp.viewer.stats().points")
        page.evaluate(_RECORD_DRAWS)
        # Pressed: a redraw draws one slice on the screen and no more while the press lasts.
        page.mouse.move(450, 300)
        page.mouse.down()
        page.evaluate("window.labelApp.viewer.recolour()")
        page.wait_for_timeout(600)
        pressed = page.evaluate("window.draws.splice(0)")
        assert len(pressed) == 1 and pressed[0]["screen"] and pressed[0]["clear"], pressed
        # Dragging: every frame is a cleared screen with one slice.
        for step in range(1, 8):
            page.mouse.move(450 + 12 * step, 300)
            page.wait_for_timeout(40)
        moving = page.evaluate("window.draws.splice(0)")
        page.mouse.up()
        _idle(page)
        resting = page.evaluate("window.draws.splice(0)")
        stats = page.evaluate("window.labelApp.viewer.stats()")
    finally:
        page.close()
    assert not errors, errors
    assert moving and all(d["screen"] and d["clear"] for d in moving), moving
    for draw in pressed + moving + resting:
        assert draw["points"] <= max(draw["limit"], largest), draw
    # At rest: into the off-screen buffer, cleared once, then slices that add up to the view.
    slices = [d for d in resting if d["points"]]
    assert not any(d["screen"] for d in resting) and resting[0]["clear"], resting
    assert len(slices) >= 2 and not any(d["clear"] for d in resting[1:]), resting
    assert sum(d["points"] for d in slices) == stats["points"] >= 0.5 * full, (resting, stats)
