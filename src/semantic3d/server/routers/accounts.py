"""Accounts: registration, login, logout, the account page (API tokens, open uploads), ``/api/me``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response

from semantic3d.server.deps import CurrentUser, PageUser
from semantic3d.server.errors import AuthenticationError, ForbiddenError, InvalidInputError
from semantic3d.server.schemas import Account, error_responses
from semantic3d.server.services.accounts import (
    authenticate,
    create_token,
    list_tokens,
    register_user,
    revoke_token,
)
from semantic3d.server.services.uploads import cancel_upload, list_uploads
from semantic3d.server.throttle import RateLimiter, limiter_in
from semantic3d.server.web import (
    ServerState,
    check_csrf,
    client_address,
    log_in,
    log_out,
    render,
    state_of,
)

router = APIRouter()


def registration_limiter(state: ServerState) -> RateLimiter:
    """The server's registrations-per-address limit."""
    settings = state.settings
    return limiter_in(
        state.extra,
        "registrations",
        limit=settings.register_max_per_ip,
        window_s=settings.register_window_s,
    )


def _local_path(target: str | None) -> str:
    """Only same-site paths may be redirect targets (no open redirects)."""
    if target and target.startswith("/") and not target.startswith("//") and "\\" not in target:
        return target
    return "/"


@router.get(
    "/api/me", response_model=Account, tags=["accounts"], responses=error_responses(401, 503)
)
def api_me(user: CurrentUser) -> Account:
    """Who the token (or session) belongs to."""
    return Account(username=user.username, is_admin=user.is_admin)


@router.get("/register", include_in_schema=False)
def register_page(request: Request, user: PageUser) -> Response:
    return render(request, "register.html", {"open": state_of(request).settings.registration_open})


@router.post("/register", include_in_schema=False)
def register(
    request: Request,
    username: str = Form(...),
    password: str = Form(...),
    password_again: str = Form(...),
    csrf_token: str = Form(""),
) -> Response:
    request.state.user = None
    check_csrf(request, csrf_token)
    state = state_of(request)
    if not state.settings.registration_open:
        raise ForbiddenError("registration is closed on this server; ask its administrator")
    try:
        if password != password_again:
            raise InvalidInputError("the two passwords differ")
        user = register_user(
            state.factory,
            state.settings,
            registration_limiter(state),
            username,
            password,
            address=client_address(request),
        )
    except InvalidInputError as exc:
        return render(
            request,
            "register.html",
            {"open": True, "error": str(exc), "username": username},
            status_code=400,
        )
    log_in(request, user)
    return RedirectResponse("/account", status_code=303)


@router.get("/login", include_in_schema=False)
def login_page(request: Request, user: PageUser, next: str = "/") -> Response:
    return render(request, "login.html", {"next": _local_path(next)})


@router.post("/login", include_in_schema=False)
def login(
    request: Request,
    username: str = Form(...),
    password: str = Form(...),
    next: str = Form("/"),
    csrf_token: str = Form(""),
) -> Response:
    request.state.user = None
    check_csrf(request, csrf_token)
    state = state_of(request)
    try:
        user = authenticate(
            state.factory, state.settings, username, password, address=client_address(request)
        )
    except AuthenticationError as exc:
        return render(
            request,
            "login.html",
            {"error": str(exc), "username": username, "next": _local_path(next)},
            status_code=401,
        )
    log_in(request, user)
    return RedirectResponse(_local_path(next), status_code=303)


@router.post("/logout", include_in_schema=False)
def logout(request: Request, csrf_token: str = Form("")) -> Response:
    check_csrf(request, csrf_token)
    log_out(request)
    return RedirectResponse("/", status_code=303)


@router.get("/account", include_in_schema=False)
def account_page(request: Request, user: PageUser) -> Response:
    if user is None:
        return RedirectResponse("/login?next=/account", status_code=303)
    response = render(request, "account.html", _account_context(request, user.id))
    response.headers["Cache-Control"] = "no-store"  # private: tokens, uploads
    return response


def _account_context(request: Request, user_id: int) -> dict[str, Any]:
    state = state_of(request)
    return {
        "tokens": list_tokens(state.factory, user_id),
        "uploads": list_uploads(state.factory, state.settings, user_id=user_id),
    }


@router.post("/account/tokens", include_in_schema=False)
def new_token(
    request: Request, user: PageUser, name: str = Form("cli"), csrf_token: str = Form("")
) -> Response:
    if user is None:
        return RedirectResponse("/login?next=/account", status_code=303)
    check_csrf(request, csrf_token)
    _, secret = create_token(state_of(request).factory, user.id, name)
    # Rendered in this response only: the secret is never stored or shown again, nor
    # kept by a browser or proxy cache (the back button asks the server again).
    response = render(
        request, "account.html", _account_context(request, user.id) | {"new_token": secret}
    )
    response.headers["Cache-Control"] = "no-store"
    return response


@router.post("/account/tokens/{token_id}/revoke", include_in_schema=False)
def revoke(request: Request, user: PageUser, token_id: int, csrf_token: str = Form("")) -> Response:
    if user is None:
        return RedirectResponse("/login?next=/account", status_code=303)
    check_csrf(request, csrf_token)
    revoke_token(state_of(request).factory, user.id, token_id)
    return RedirectResponse("/account", status_code=303)


@router.post("/account/uploads/{upload_id}/delete", include_in_schema=False)
def delete_upload_form(
    request: Request, user: PageUser, upload_id: str, csrf_token: str = Form("")
) -> Response:
    if user is None:
        return RedirectResponse("/login?next=/account", status_code=303)
    check_csrf(request, csrf_token)
    state = state_of(request)
    cancel_upload(state.factory, state.settings, upload_id, user_id=user.id)
    return RedirectResponse("/account", status_code=303)
