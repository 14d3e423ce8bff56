"""The routers' dependencies, as ``Annotated`` aliases for FastAPI's ``Depends``.

``def route(user: CurrentUser, db: DbSession, state: State)``: FastAPI resolves who is
asking, opens a database session for the request and closes it afterwards, and the
route body only calls the services. :mod:`semantic3d.server.web` holds the functions.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from semantic3d.server.errors import ForbiddenError
from semantic3d.server.models import User
from semantic3d.server.web import ServerState, api_user, optional_user, session_user, state_of


async def server_state(request: Request) -> ServerState:
    """The app's :class:`ServerState` (async: answered on the event loop, no thread hop)."""
    return state_of(request)


def db_session(request: Request) -> Iterator[Session]:
    """A database session for one request (closed when the request is done)."""
    with state_of(request).factory() as session:
        yield session


def page_user(request: Request) -> User | None:
    """The account logged in by cookie (``None``: anonymous), also shown by the page."""
    user = request.state.user = session_user(request)
    return user


def admin_user(request: Request) -> User:
    """The logged-in administrator of an admin page; :class:`ForbiddenError` for anyone else."""
    user = page_user(request)
    if user is None or not user.is_admin:
        raise ForbiddenError("this page is for administrators")
    return user


State = Annotated[ServerState, Depends(server_state)]
"""Everything the routers share (settings, session factory, caches)."""

DbSession = Annotated[Session, Depends(db_session)]
"""A database session for the request."""

CurrentUser = Annotated[User, Depends(api_user)]
"""The caller of an API route: a token, or the session (plus CSRF header if unsafe); 401 else."""

OptionalUser = Annotated[User | None, Depends(optional_user)]
"""The caller if authenticated by token or session, else ``None``."""

PageUser = Annotated[User | None, Depends(page_user)]
"""The account of a web page's visitor (session cookie), ``None`` when anonymous."""

AdminUser = Annotated[User, Depends(admin_user)]
"""The administrator of an admin page (403 for anyone else)."""
