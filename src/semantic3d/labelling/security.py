"""The local app's guard: loopback Host names only, a per-launch secret, same-origin writes.

The labelling app listens on a loopback address, but any web page the user opens and any
local process can reach that address. :class:`LocalGuard` (a pure ASGI middleware) closes
the ways in:

- **Host**: only ``127.0.0.1:PORT``, ``localhost:PORT`` and ``[::1]:PORT`` are served (a
  DNS-rebinding page arrives under its own host name and is refused with 421);
- **secret**: every ``/api`` request carries the per-launch secret in the
  ``X-Semantic3D-Token`` header (403 otherwise). The command prints it once in the
  address (``/?token=...``); the page moves it into the header of every call and strips
  it from the address bar. A cross-site page cannot set that header without a CORS
  preflight, which the app never grants, and does not know the secret;
- **Origin**: a request that changes state (anything but GET / HEAD) must come from the
  app's own origin when it names one (403 otherwise);
- **size**: request bodies above ``max_body_bytes`` are refused (413), and a state-changing
  request must declare its length (411).

The page and its static files load without the secret; they hold nothing of the scan.
Every answer carries ``Referrer-Policy: no-referrer`` (the address holds the secret until
the page strips it), ``X-Content-Type-Options: nosniff`` and a frame ban.
"""

from __future__ import annotations

import json
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

__all__ = ["TOKEN_HEADER", "LocalGuard", "allowed_hosts", "new_secret"]

TOKEN_HEADER = "X-Semantic3D-Token"
_TOKEN_KEY = TOKEN_HEADER.lower().encode("latin-1")
_SAFE_METHODS = frozenset({"GET", "HEAD"})

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def new_secret() -> str:
    """A fresh random secret for one launch (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


def allowed_hosts(port: int) -> frozenset[str]:
    """The Host header values a loopback app on ``port`` answers."""
    return frozenset({f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}"})


class LocalGuard:
    """ASGI middleware enforcing the rules of the module docstring around ``app``."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        port: int,
        secret: str,
        max_body_bytes: int = 1 << 20,
        content_security_policy: str | None = None,
    ) -> None:
        if len(secret) < 16:
            raise ValueError("secret: expected at least 16 characters")
        self.app = app
        self.hosts = allowed_hosts(port)
        self.origins = frozenset(f"http://{host}" for host in self.hosts)
        self.secret = secret.encode("latin-1")
        self.max_body_bytes = max_body_bytes
        self.extra_headers = [
            (b"referrer-policy", b"no-referrer"),
            (b"x-content-type-options", b"nosniff"),
            (b"x-frame-options", b"DENY"),
        ]
        if content_security_policy:
            self.extra_headers.append(
                (b"content-security-policy", content_security_policy.encode("latin-1"))
            )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008})
                return
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope)
        if refusal is not None:
            status, message = refusal
            await self._answer(send, status, message)
            return

        extra = self.extra_headers
        if str(scope.get("path", "")).startswith("/api"):
            extra = [*extra, (b"cache-control", b"no-store")]

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), *extra]
            await send(message)

        await self.app(scope, receive, send_with_headers)

    def _refusal(self, scope: Scope) -> tuple[int, str] | None:
        headers: dict[bytes, bytes] = {}
        for key, value in scope.get("headers", []):
            headers.setdefault(bytes(key).lower(), bytes(value))
        host = headers.get(b"host", b"").decode("latin-1")
        if host not in self.hosts:
            return 421, (
                f"unexpected Host {host!r}: this app answers only " + ", ".join(sorted(self.hosts))
            )
        method = str(scope.get("method", "GET")).upper()
        path = str(scope.get("path", "/"))
        if path == "/api" or path.startswith("/api/"):
            token = headers.get(_TOKEN_KEY, b"")
            if not secrets.compare_digest(token, self.secret):
                return 403, (
                    "missing or wrong token: open the address the command printed "
                    "(it ends with ?token=...)"
                )
        if method not in _SAFE_METHODS:
            origin = headers.get(b"origin")
            if origin is not None and origin.decode("latin-1") not in self.origins:
                return 403, f"cross-origin request from {origin.decode('latin-1')!r} refused"
            if b"transfer-encoding" in headers:
                return 411, "expected a Content-Length, found a chunked body"
            length = headers.get(b"content-length", b"0")
            try:
                size = int(length)
            except ValueError:
                return 400, f"expected a numeric Content-Length, found {length!r}"
            if size > self.max_body_bytes:
                return 413, (
                    f"request body of {size} bytes refused (at most {self.max_body_bytes})"
                )
        return None

    async def _answer(self, send: Send, status: int, message: str) -> None:
        body = json.dumps({"detail": message}).encode("utf-8")
        await send(
            {
                "type": "http.response.start",
                "status": status,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode("latin-1")),
                    (b"cache-control", b"no-store"),
                    *self.extra_headers,
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
