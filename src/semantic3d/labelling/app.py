"""The labelling / viewing web app: ``create_label_app(session)`` -> FastAPI.

Routes only parse requests and call :class:`~semantic3d.labelling.session.LabelSession`;
the page (``static/``, plain ES modules and the vendored three.js) is served as files.
Errors of the session become 4xx answers carrying the message (``{"detail": ...}``).

Every ``/api`` call carries the launch's secret in the ``X-Semantic3D-Token`` header,
state-changing calls come from the app's own origin, and only loopback Host names are
served (:class:`~semantic3d.labelling.security.LocalGuard`). Request bodies are checked
by pydantic; a bad one is answered 422 with one line naming the field, what was expected
and what was found (never echoing NaN or a huge input back).

API (JSON unless noted; coordinates are metres re-centred on ``origin``):

==========================  ====================================================
``GET /api/scan``           hierarchy (origin, bounds, nodes), classes, summary
``GET /api/nodes/{id}``     binary: float32 xyz × n, rgb × n, intensity × n
``GET /api/nodes/{id}/state`` binary: class × n, working flag × n, prediction × n
``GET /api/summary``        layer counts, working set size, undo/redo availability
``POST /api/split``         ``{view_projection: 16 numbers row-major, polygon, keep}``
``POST /api/split-mask``    ``{view_projection, width, height, mask: base64 bits, keep}``
                            (a lasso or brush stroke rasterised on the screen)
``POST /api/fit``           ``{kind, seeds: [[x, y, z]], tolerance_m, radius_m?, region?, model?}``
                            (region: ``{kind: "sphere", centre, radius_m}`` or
                            ``{kind: "box", min, max}``; model: a previewed one to commit)
``POST /api/fit/preview``   same body: the model, its inliers' count, rms and a sample
``GET /api/progress``       the running operation: ``{running, operation, done, total, …}``
``POST /api/cancel``        ask it to stop (409 ``cancelled`` answers the operation)
``POST /api/stats``         ``{scope: "working" | "view", view_projection?}``: counts per
                            class, confusion of prediction against labels, scores
``POST /api/assign``        ``{value, confirm_whole_scan?}`` (409 ``confirm`` when unconfirmed
                            and the working set is the whole scan)
``POST /api/reset``         ``{scope: "all" | "unlabelled"}``
``POST /api/move-layer``    ``{source, target}``
``POST /api/layers/{value}`` ``{hidden?, locked?}``
``POST /api/undo`` · ``/api/redo`` · ``/api/save`` ``{path?, overwrite?}``
``GET /api/history``        the journal's entries
==========================  ====================================================
"""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from semantic3d.core.errors import require

require("fastapi", "label")

import numpy as np  # noqa: E402
from fastapi import FastAPI, HTTPException, Request, Response  # noqa: E402
from fastapi.exceptions import RequestValidationError  # noqa: E402
from fastapi.responses import FileResponse, JSONResponse  # noqa: E402
from fastapi.staticfiles import StaticFiles  # noqa: E402
from pydantic import BaseModel, Field  # noqa: E402

from semantic3d.core.classes import CLASSES, UNLABELLED  # noqa: E402
from semantic3d.core.errors import OutputExistsError, Semantic3DError, ShapeError  # noqa: E402
from semantic3d.labelling.errors import (  # noqa: E402
    OperationCancelledError,
    OperationError,
    ReadOnlyError,
    WholeScanError,
)
from semantic3d.labelling.fitting import Region  # noqa: E402
from semantic3d.labelling.security import LocalGuard, new_secret  # noqa: E402
from semantic3d.labelling.session import (  # noqa: E402
    MAX_RADIUS_M,
    MAX_SEEDS,
    MAX_TOLERANCE_M,
    LabelSession,
)

__all__ = ["MAX_POLYGON_VERTICES", "STATIC_DIR", "create_label_app"]

STATIC_DIR = Path(__file__).parent / "static"
MAX_POLYGON_VERTICES = 5000

Finite = Annotated[float, Field(allow_inf_nan=False)]


class SplitRequest(BaseModel):
    view_projection: list[Finite] = Field(min_length=16, max_length=16)
    polygon: list[tuple[Finite, Finite]] = Field(min_length=3, max_length=MAX_POLYGON_VERTICES)
    keep: Literal["inside", "outside"] = "inside"


Point = tuple[Finite, Finite, Finite]


class RegionRequest(BaseModel):
    kind: Literal["sphere", "box"]
    centre: Point | None = None
    radius_m: float | None = Field(default=None, gt=0, le=MAX_RADIUS_M, allow_inf_nan=False)
    min: Point | None = None
    max: Point | None = None

    def region(self) -> Region:
        return Region.from_dict(self.model_dump())


class MaskSplitRequest(BaseModel):
    view_projection: list[Finite] = Field(min_length=16, max_length=16)
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)
    mask: str = Field(max_length=1_000_000, description="base64 of the packed bits")
    keep: Literal["inside", "outside"] = "inside"


class FitRequest(BaseModel):
    kind: Literal["plane", "line", "cylinder", "sphere"]
    seeds: list[Point] = Field(min_length=1, max_length=MAX_SEEDS)
    tolerance_m: float = Field(gt=0, le=MAX_TOLERANCE_M, allow_inf_nan=False)
    radius_m: float | None = Field(default=None, gt=0, le=MAX_RADIUS_M, allow_inf_nan=False)
    region: RegionRequest | None = None
    model: dict[str, Any] | None = None


class StatsRequest(BaseModel):
    scope: Literal["working", "view"] = "working"
    view_projection: list[Finite] | None = Field(default=None, min_length=16, max_length=16)


class AssignRequest(BaseModel):
    value: int
    confirm_whole_scan: bool = False


class ResetRequest(BaseModel):
    scope: Literal["all", "unlabelled"] = "all"


class MoveLayerRequest(BaseModel):
    source: int
    target: int


class LayerRequest(BaseModel):
    hidden: bool | None = None
    locked: bool | None = None


class SaveRequest(BaseModel):
    path: str | None = None
    overwrite: bool = False


def _validation_message(exc: RequestValidationError) -> str:
    """One line from pydantic's first error: the field, what was expected, what was found."""
    errors = exc.errors()
    if not errors:
        return "invalid request"
    first = errors[0]
    location = ".".join(str(part) for part in first.get("loc", ()) if part != "body")
    found = repr(first.get("input"))
    if len(found) > 40:
        found = found[:37] + "..."
    if first.get("type") in ("too_long", "too_short"):
        found = f"{len(first['input'])} items" if hasattr(first.get("input"), "__len__") else found
    message = str(first.get("msg", "invalid value"))
    more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
    return f"{location or 'body'}: {message[:1].lower()}{message[1:]}, found {found}{more}"


def _content_security_policy() -> str:
    """Scripts from the app only, plus the page's inline import map (by its hash)."""
    page = (STATIC_DIR / "index.html").read_text(encoding="utf-8")
    hashes = [
        "'sha256-" + base64.b64encode(hashlib.sha256(m.encode()).digest()).decode() + "'"
        for m in re.findall(r"<script type=\"importmap\">(.*?)</script>", page, re.DOTALL)
    ]
    return (
        f"default-src 'self'; script-src 'self' {' '.join(hashes)}; "
        "style-src 'self' 'unsafe-inline'; img-src 'self' data:; connect-src 'self'; "
        "object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
    )


def create_label_app(
    session: LabelSession, *, port: int, secret: str | None = None, title: str | None = None
) -> FastAPI:
    """The app serving ``session`` on loopback ``port``: the page at ``/``, its API under ``/api``.

    ``secret`` (default: a fresh random one, kept in ``app.state.secret``) must come with
    every API call; see :mod:`~semantic3d.labelling.security`.
    """
    app = FastAPI(title=title or "semantic3d labelling", docs_url=None, redoc_url=None)
    app.state.session = session
    app.state.secret = secret or new_secret()
    app.state.port = port
    app.add_middleware(
        LocalGuard,
        port=port,
        secret=app.state.secret,
        content_security_policy=_content_security_policy(),
    )
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    octet = "application/octet-stream"

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _validation_message(exc)}, status_code=422)

    @app.exception_handler(Semantic3DError)
    async def _errors(request: Request, exc: Semantic3DError) -> JSONResponse:
        if isinstance(exc, WholeScanError):
            return JSONResponse({"detail": str(exc), "confirm": True}, status_code=409)
        if isinstance(exc, OperationCancelledError):
            return JSONResponse({"detail": str(exc), "cancelled": True}, status_code=409)
        status = 400
        if isinstance(exc, ReadOnlyError):
            status = 403
        elif isinstance(exc, OutputExistsError):
            status = 409
        elif not isinstance(exc, OperationError | ShapeError):
            status = 422
        return JSONResponse({"detail": str(exc)}, status_code=status)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-store"})

    @app.get("/api/scan")
    def scan() -> dict[str, Any]:
        return {
            "name": session.scan.path.name,
            "hierarchy": session.lod.hierarchy(),
            "classes": [
                {"value": c.value, "name": c.name, "colour": c.hex_colour}
                for c in (UNLABELLED, *CLASSES)
            ],
            "summary": session.summary(),
        }

    @app.get("/api/summary")
    def summary() -> dict[str, Any]:
        return session.summary()

    @app.get("/api/nodes/{node_id}")
    def node(node_id: int) -> Response:
        try:
            return Response(session.node_points(node_id), media_type=octet)
        except KeyError:
            raise HTTPException(404, f"no node {node_id}") from None

    @app.get("/api/nodes/{node_id}/state")
    def node_state(node_id: int) -> Response:
        try:
            return Response(session.node_state(node_id), media_type=octet)
        except KeyError:
            raise HTTPException(404, f"no node {node_id}") from None

    def answer(result: Any) -> dict[str, Any]:
        return {"result": result.to_dict(), "summary": session.summary()}

    @app.post("/api/split")
    def split(request: SplitRequest) -> dict[str, Any]:
        return answer(session.split(request.view_projection, request.polygon, keep=request.keep))

    @app.post("/api/split-mask")
    def split_mask(request: MaskSplitRequest) -> dict[str, Any]:
        try:
            bits = np.frombuffer(base64.b64decode(request.mask, validate=True), np.uint8)
        except ValueError:
            raise OperationError("mask: expected base64 text, found something else") from None
        return answer(
            session.split_mask(
                request.view_projection,
                bits,
                width=request.width,
                height=request.height,
                keep=request.keep,
            )
        )

    @app.post("/api/fit")
    def fit(request: FitRequest) -> dict[str, Any]:
        return answer(
            session.fit(
                request.kind,
                request.seeds,
                tolerance_m=request.tolerance_m,
                radius_m=request.radius_m,
                region=None if request.region is None else request.region.region(),
                model=request.model,
            )
        )

    @app.post("/api/fit/preview")
    def fit_preview(request: FitRequest) -> dict[str, Any]:
        preview = session.fit_preview(
            request.kind,
            request.seeds,
            tolerance_m=request.tolerance_m,
            radius_m=request.radius_m,
            region=None if request.region is None else request.region.region(),
        )
        return preview.to_dict()

    @app.get("/api/progress")
    def progress() -> dict[str, Any]:
        return session.progress.snapshot()

    @app.post("/api/cancel")
    def cancel() -> dict[str, Any]:
        return {"cancelled": session.cancel()}

    @app.post("/api/stats")
    def stats(request: StatsRequest) -> dict[str, Any]:
        from semantic3d.labelling.stats import selection_stats

        return selection_stats(
            session, scope=request.scope, view_projection=request.view_projection
        )

    @app.post("/api/assign")
    def assign(request: AssignRequest) -> dict[str, Any]:
        return answer(session.assign(request.value, confirm_whole_scan=request.confirm_whole_scan))

    @app.post("/api/reset")
    def reset(request: ResetRequest) -> dict[str, Any]:
        return answer(session.reset(scope=request.scope))

    @app.post("/api/move-layer")
    def move_layer(request: MoveLayerRequest) -> dict[str, Any]:
        return answer(session.move_layer(request.source, request.target))

    @app.post("/api/layers/{value}")
    def layer(value: int, request: LayerRequest) -> dict[str, Any]:
        session.set_layer(value, hidden=request.hidden, locked=request.locked)
        return {"summary": session.summary()}

    @app.post("/api/undo")
    def undo() -> dict[str, Any]:
        return answer(session.undo())

    @app.post("/api/redo")
    def redo() -> dict[str, Any]:
        return answer(session.redo())

    @app.post("/api/save")
    def save(request: SaveRequest) -> dict[str, Any]:
        path = session.save(request.path, overwrite=request.overwrite)
        return {"path": str(path), "summary": session.summary()}

    @app.get("/api/history")
    def history() -> list[dict[str, Any]]:
        return [] if session.journal is None else session.journal.operations()

    return app
