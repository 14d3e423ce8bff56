"""``create_app(settings)``: the FastAPI application of the benchmark server."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.sessions import SessionMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from semantic3d import __version__
from semantic3d.core.errors import Semantic3DError, SubmissionError
from semantic3d.server.db import (
    create_db_engine,
    create_session_factory,
    database_error,
    run_migrations,
)
from semantic3d.server.errors import (
    ConflictError,
    ServerError,
    ServiceUnavailableError,
    ThrottledError,
)
from semantic3d.server.routers import accounts, admin, challenges, submissions, uploads
from semantic3d.server.routers.apidocs import API_DOCS_PATH, OPENAPI_PATH
from semantic3d.server.routers.apidocs import router as api_docs_router
from semantic3d.server.schemas import Health
from semantic3d.server.services.accounts import dummy_hash
from semantic3d.server.services.challenges import ChallengeCache
from semantic3d.server.services.leaderboard import LeaderboardCache
from semantic3d.server.services.recovery import recover_stored_files
from semantic3d.server.settings import Settings, load_settings
from semantic3d.server.web import STATIC_DIR, ServerState, build_templates, render
from semantic3d.server.worker import Worker, WorkerThread

logger = logging.getLogger(__name__)

_SECURITY_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"same-origin"),
    (
        b"content-security-policy",
        b"default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
        b"frame-ancestors 'none'; form-action 'self'",
    ),
]


# The Swagger page is served from the package (routers/apidocs.py): scripts from 'self'
# only; Swagger UI sets inline styles, so only this page allows them.
_API_DOCS_HEADERS = [
    *_SECURITY_HEADERS[:-1],
    (
        b"content-security-policy",
        b"default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; "
        b"script-src 'self'; frame-ancestors 'none'; form-action 'self'",
    ),
]


class SecurityHeadersMiddleware:
    """Adds conservative security headers to every response (plain ASGI: no overhead)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = _API_DOCS_HEADERS if scope["path"] == API_DOCS_PATH else _SECURITY_HEADERS

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = list(message.get("headers", [])) + extra
            await send(message)

        await self.app(scope, receive, send_with_headers)


# Bodies other than upload chunks (forms, JSON method cards) are read into memory by the
# framework, so they get a small cap; upload chunks stream to disk under their own caps.
MAX_BODY_BYTES = 1 << 20


def _streams_to_disk(scope: Scope) -> bool:
    return scope["method"] == "PUT" and str(scope["path"]).startswith("/api/uploads/")


class BodyLimitMiddleware:
    """Refuses request bodies over :data:`MAX_BODY_BYTES` (413) without reading them whole.

    A declared ``Content-Length`` over the cap is refused before any byte is read; a body
    without one (chunked, e.g. through a proxy that streams) is counted as it arrives and
    refused at the first byte over the cap.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] in ("GET", "HEAD", "OPTIONS")
            or _streams_to_disk(scope)
        ):
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > MAX_BODY_BYTES:
            message = _body_too_large(int(declared))
            response: Response
            if str(scope["path"]).startswith("/api/"):
                response = JSONResponse({"error": message}, status_code=413)
            else:
                response = PlainTextResponse(message, status_code=413)
            await response(scope, receive, send)
            return
        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > MAX_BODY_BYTES:
                    # FastAPI passes an HTTPException raised while reading the body through
                    # to the app's handlers (JSON under /api/, an error page elsewhere).
                    raise StarletteHTTPException(413, _body_too_large(received, more=True))
            return message

        await self.app(scope, counting_receive, send)


def _body_too_large(n_bytes: int, *, more: bool = False) -> str:
    return (
        f"request body of {n_bytes}{'+' if more else ''} bytes: at most {MAX_BODY_BYTES} "
        "bytes here (submissions go through /api/uploads)"
    )


def create_app(settings: Settings | None = None) -> FastAPI:
    """The server for ``settings`` (default: from ``SEMANTIC3D_*`` environment variables).

    Creates the data dir, upgrades the database schema, gives the files of finalizes
    that a crash interrupted back to their uploads (:mod:`.services.recovery`), and, when
    ``settings.runs_embedded_worker``, runs an evaluation worker on a background thread
    for the lifetime of the app.
    """
    settings = settings or load_settings()
    settings.prepare_data_dir()
    engine = create_db_engine(settings)
    run_migrations(engine)
    factory = create_session_factory(engine)
    dummy_hash()  # before any login: the first unknown name costs what the others do
    recovered = recover_stored_files(factory, settings)
    if recovered.restored or recovered.set_aside:
        logger.warning(
            "start-up: %d interrupted finalize(s) given back to their uploads, %d stored "
            "file(s) set aside in %s",
            len(recovered.restored),
            len(recovered.set_aside),
            settings.orphaned_dir,
        )
    state = ServerState(
        settings=settings,
        engine=engine,
        factory=factory,
        challenges=ChallengeCache(settings),
        leaderboards=LeaderboardCache(factory, settings.leaderboard_cache_s),
        templates=build_templates(settings),
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.runs_embedded_worker:
            state.worker = WorkerThread(Worker(settings, factory, cache=state.challenges))
            state.worker.start()
            logger.info("embedded worker started")
        try:
            yield
        finally:
            if state.worker is not None:
                state.worker.stop()
                state.worker = None
            engine.dispose()

    app = FastAPI(
        title=settings.site_title,
        version=__version__,
        lifespan=lifespan,
        docs_url=None,  # served from the package by routers/apidocs.py (works offline)
        redoc_url=None,
        openapi_url=OPENAPI_PATH,
    )
    app.state.server = state
    app.add_middleware(
        SessionMiddleware,
        secret_key=settings.resolved_secret_key(),
        session_cookie="semantic3d_session",
        max_age=settings.session_max_age_s,
        same_site="lax",
        https_only=settings.cookie_secure,
    )
    app.add_middleware(BodyLimitMiddleware)
    app.add_middleware(SecurityHeadersMiddleware)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    for router in (challenges, accounts, uploads, submissions, admin):
        app.include_router(router.router)
    app.include_router(api_docs_router)
    _install_error_handlers(app)

    @app.get("/api/health", response_model=Health, tags=["health"])
    def health() -> Health:
        """Liveness: the server answers, and its version."""
        return Health(status="ok", version=__version__)

    return app


def _wants_json(request: Request) -> bool:
    return request.url.path.startswith("/api/")


def _error_response(
    request: Request,
    status: int,
    message: str,
    *,
    problems: list[str] | None = None,
    headers: dict[str, str] | None = None,
    extra: dict[str, Any] | None = None,
) -> Response:
    if _wants_json(request):
        body: dict[str, Any] = {"error": message}
        if problems is not None:
            body["problems"] = problems
        body.update(extra or {})
        return JSONResponse(body, status_code=status, headers=headers)
    if getattr(request.state, "user", None) is None:
        request.state.user = None
    response = render(
        request,
        "error.html",
        {"status": status, "message": message, "problems": problems or []},
        status_code=status,
    )
    for key, value in (headers or {}).items():
        response.headers[key] = value
    return response


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(SubmissionError)
    async def _submission(request: Request, exc: SubmissionError) -> Response:
        head = f"{exc.source}: " if exc.source else ""
        return _error_response(
            request,
            422,
            f"{head}invalid submission, {len(exc.problems)} problem(s)",
            problems=list(exc.problems),
        )

    @app.exception_handler(ServerError)
    async def _server(request: Request, exc: ServerError) -> Response:
        headers = None
        extra: dict[str, Any] = {}
        if isinstance(exc, ThrottledError | ServiceUnavailableError):
            headers = {"Retry-After": str(exc.retry_after_s)}
            extra["retry_after_s"] = exc.retry_after_s
        if isinstance(exc, ConflictError) and exc.offset is not None:
            extra["offset"] = exc.offset
        return _error_response(request, exc.status_code, str(exc), headers=headers, extra=extra)

    @app.exception_handler(OperationalError)
    async def _database(request: Request, exc: OperationalError) -> Response:
        # A locked (503) or full (507) database outside a write transaction; else a bug.
        error = database_error(exc)
        if not isinstance(error, ServerError):
            logger.error("database error", exc_info=exc)
            return _error_response(request, 500, "internal server error")
        return await _server(request, error)

    @app.exception_handler(Semantic3DError)
    async def _package(request: Request, exc: Semantic3DError) -> Response:
        status = 422 if isinstance(exc, ValueError) else 400
        return _error_response(request, status, str(exc))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> Response:
        problems = []
        for error in exc.errors():
            where = ".".join(str(part) for part in error.get("loc", ()))
            problems.append(f"{where}: {error.get('msg', 'invalid')}")
        return _error_response(request, 422, "malformed request", problems=problems)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        message = str(exc.detail)
        if exc.status_code == 400 and "parsing the body" in message:
            message = "malformed request body: expected UTF-8 JSON (or form data)"
        headers = dict(exc.headers) if exc.headers else None
        return _error_response(request, exc.status_code, message, headers=headers)
