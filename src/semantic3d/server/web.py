"""Shared request plumbing for the routers: app state, who is asking, CSRF, templates.

Two ways to authenticate: the session cookie of the web pages (signed by Starlette's
``SessionMiddleware``) and ``Authorization: Bearer s3d_…`` API tokens for the CLI. A
state-changing request authenticated by cookie must carry the session's CSRF token
(form field ``csrf_token`` or header ``X-CSRF-Token``); token requests need none, as
browsers never attach them on their own.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.templating import Jinja2Templates
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.core.classes import CLASSES
from semantic3d.server.errors import AuthenticationError, ForbiddenError
from semantic3d.server.formatting import (
    format_percent,
    format_seconds,
    format_seconds_plain,
    plural,
    render_markdown,
    render_markdown_inline,
)
from semantic3d.server.models import User
from semantic3d.server.services.accounts import end_sessions, get_user, user_for_token
from semantic3d.server.services.challenges import ChallengeCache
from semantic3d.server.services.leaderboard import LeaderboardCache
from semantic3d.server.settings import Settings
from semantic3d.server.worker import WorkerThread

TEMPLATES_DIR = Path(__file__).parent / "templates"
STATIC_DIR = Path(__file__).parent / "static"
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


@dataclass
class ServerState:
    """Everything the routers share, kept on ``app.state.server``."""

    settings: Settings
    engine: Engine
    factory: sessionmaker[Session]
    challenges: ChallengeCache
    leaderboards: LeaderboardCache
    templates: Jinja2Templates
    worker: WorkerThread | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def state_of(request: Request) -> ServerState:
    """The :class:`ServerState` of the app serving ``request``."""
    state: ServerState = request.app.state.server
    return state


def client_address(request: Request) -> str:
    """The peer address (behind a proxy, run uvicorn with ``--forwarded-allow-ips``)."""
    return request.client.host if request.client else "unknown"


def csrf_token(request: Request) -> str:
    """The session's CSRF token (created on first use)."""
    token = request.session.get("csrf")
    if not token:
        token = secrets.token_urlsafe(32)
        request.session["csrf"] = token
    return str(token)


def check_csrf(request: Request, submitted: str | None) -> None:
    """Raise :class:`ForbiddenError` unless ``submitted`` is the session's CSRF token."""
    expected = request.session.get("csrf")
    if not expected or not submitted or not hmac.compare_digest(str(expected), submitted):
        raise ForbiddenError(
            "missing or wrong CSRF token: reload the page and try again "
            "(API clients: send Authorization: Bearer <token>)"
        )


def bearer_token(request: Request) -> str | None:
    """The API token of an ``Authorization: Bearer`` header, if any."""
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    return value.strip() if scheme.lower() == "bearer" and value.strip() else None


def session_user(request: Request) -> User | None:
    """The account logged in through the session cookie, if any."""
    user_id = request.session.get("user_id")
    if not isinstance(user_id, int):
        return None
    user = get_user(state_of(request).factory, user_id)
    if user is None or request.session.get("epoch") != _epoch(user):
        request.session.clear()
        return None
    return user


def api_user(request: Request) -> User:
    """The caller of an API route: a token, or the session (plus CSRF header if unsafe)."""
    token = bearer_token(request)
    if token is not None:
        return user_for_token(state_of(request).factory, token)
    user = session_user(request)
    if user is None:
        raise AuthenticationError(
            "authentication required: send Authorization: Bearer <token> "
            "(create one on your account page) or log in"
        )
    if request.method not in _SAFE_METHODS:
        check_csrf(request, request.headers.get("x-csrf-token"))
    return user


def optional_user(request: Request) -> User | None:
    """The caller if authenticated by token or session, else ``None`` (public pages)."""
    token = bearer_token(request)
    if token is not None:
        return user_for_token(state_of(request).factory, token)
    return session_user(request)


def _epoch(user: User) -> str:
    """Changes when the password changes or the account logs out; reveals no hash."""
    material = f"{user.session_epoch}:{user.password_hash}"
    return hashlib.sha256(material.encode()).hexdigest()[:16]


def log_in(request: Request, user: User) -> None:
    """Start a fresh session for ``user`` (new CSRF token: no session fixation)."""
    request.session.clear()
    request.session["user_id"] = user.id
    request.session["epoch"] = _epoch(user)
    csrf_token(request)


def log_out(request: Request) -> None:
    """End the session, and every other session of its account (copied cookies included)."""
    user_id = request.session.get("user_id")
    request.session.clear()
    if isinstance(user_id, int):
        end_sessions(state_of(request).factory, user_id)


def build_templates(settings: Settings) -> Jinja2Templates:
    """The Jinja2 environment of the pages (autoescaping on)."""
    templates = Jinja2Templates(directory=str(TEMPLATES_DIR))
    env = templates.env
    env.globals["site_title"] = settings.site_title
    env.globals["classes"] = CLASSES
    env.globals["csrf_token"] = csrf_token
    env.filters["pct"] = format_percent
    env.filters["when"] = lambda value: "" if value is None else f"{value:%Y-%m-%d %H:%M} UTC"
    env.filters["day"] = lambda value: "" if value is None else f"{value:%Y-%m-%d}"
    env.filters["seconds"] = format_seconds
    env.filters["seconds_plain"] = format_seconds_plain
    env.filters["plural"] = plural
    env.filters["markdown"] = render_markdown
    env.filters["markdown_inline"] = render_markdown_inline
    env.filters["filesize"] = format_bytes
    env.filters["duration"] = format_duration
    return templates


def format_bytes(n_bytes: int | None) -> str:
    """A byte count for people, in binary units.

    >>> format_bytes(1_503_238_554), format_bytes(8 << 30), format_bytes(512)
    ('1.4 GiB', '8 GiB', '512 bytes')
    """
    if n_bytes is None:
        return "–"
    if n_bytes < 1024:
        return f"{n_bytes} bytes"
    value = float(n_bytes)
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        value /= 1024
        if value < 1024 or unit == "TiB":
            break
    text = f"{value:.1f}"
    return f"{text.removesuffix('.0')} {unit}"


def format_duration(seconds: float | None) -> str:
    """A wait for people, to the minute (rounded up).

    >>> format_duration(59), format_duration(3 * 3600 + 12 * 60), format_duration(2 * 86400 + 5 * 3600)
    ('1 min', '3 h 12 min', '2 d 5 h')
    """
    if seconds is None:
        return "–"
    minutes = max(1, -(-int(seconds) // 60))
    days, minutes = divmod(minutes, 1440)
    hours, minutes = divmod(minutes, 60)
    if days:
        return f"{days} d {hours} h" if hours else f"{days} d"
    if hours:
        return f"{hours} h {minutes} min" if minutes else f"{hours} h"
    return f"{minutes} min"


def render(
    request: Request, name: str, context: dict[str, Any] | None = None, *, status_code: int = 200
) -> Any:
    """Render template ``name`` with the current user in the context."""
    values = {"user": getattr(request.state, "user", None)}
    values.update(context or {})
    return state_of(request).templates.TemplateResponse(
        request, name, values, status_code=status_code
    )
