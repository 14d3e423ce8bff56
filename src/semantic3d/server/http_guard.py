"""A guard in front of uvicorn's HTTP parser: header size, header time, connection count.

uvicorn runs the ``httptools`` parser (``uvicorn[standard]``), which has no limit on a
request's head and joins a header's pieces with ``bytes +=`` as they arrive: one 48 MiB
header costs seconds of CPU on the event loop, before any authentication, and 256 MiB
ones cost minutes (quadratic). uvicorn has no limit for it (``h11_max_incomplete_event_
size`` is for the slower pure-Python h11 parser), no time limit on a request head, and
its ``limit_concurrency`` answers 503 only once a head is complete, so half-sent requests
hold their sockets until the process runs out of file descriptors. Hence this subclass
of uvicorn's own protocol, which

- holds a request's head back from the parser until it is complete (the blank line that
  ends it has arrived), so the parser sees it in one piece: linear work, one copy;
- answers ``431`` and closes once more than ``max_header_bytes`` arrive without the end
  of the head (the request line and headers together);
- closes a connection whose head has not arrived ``header_timeout_s`` after its first
  byte (or after the connection opened), with ``408`` when part of it came;
- keeps at most ``max_connections`` open: a new connection over the cap closes the
  connection that has waited longest for a request head (a half-sent one, or one idle
  between requests), so a flood of half-sent requests can never keep ``/api/health``
  or anyone else out; when every connection is busy with a request, the new one gets
  ``503``.

Hand-written because uvicorn offers none of this for its fast parser and the server's
process must not need a second proxy in front to survive one client.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

_HEAD_ENDS = (b"\r\n\r\n", b"\n\n")


@dataclass(frozen=True, slots=True)
class ConnectionLimits:
    """What one connection may spend before its request reaches the application."""

    max_header_bytes: int = 64 << 10
    header_timeout_s: float = 10.0
    max_connections: int = 1000


def _response(status: int, reason: str, message: str, *extra: str) -> bytes:
    body = message.encode()
    head = [
        f"HTTP/1.1 {status} {reason}",
        "content-type: text/plain; charset=utf-8",
        f"content-length: {len(body)}",
        "connection: close",
        *extra,
    ]
    return ("\r\n".join(head) + "\r\n\r\n").encode() + body


def guarded_protocol(limits: ConnectionLimits) -> type[asyncio.Protocol]:
    """An ``http`` protocol class for ``uvicorn.Config`` enforcing ``limits``.

    Each call makes a class with its own register of connections, so two servers in one
    process do not share a cap.
    """
    # Connections waiting for a request head, oldest first (a dict keeps insertion order).
    waiting: dict[GuardedProtocol, None] = {}
    too_large = _response(
        431,
        "Request Header Fields Too Large",
        f"request line and headers over {limits.max_header_bytes} bytes\n",
    )
    too_slow = _response(
        408,
        "Request Timeout",
        f"request line and headers not received within {limits.header_timeout_s:g} s\n",
    )
    busy = _response(
        503,
        "Service Unavailable",
        "too many connections; try again in a moment\n",
        "retry-after: 1",
    )

    class GuardedProtocol(HttpToolsProtocol):
        """uvicorn's httptools protocol behind the guard (see the module docstring)."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._head = bytearray()
            self._head_bytes = 0
            self._in_head = True  # the next bytes belong to a request head
            self._deadline: asyncio.TimerHandle | None = None

        # The connection -----------------------------------------------------------------
        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            if len(self.connections) > limits.max_connections:
                oldest = next(iter(waiting), None)
                if oldest is None:
                    self._refuse(busy)
                    return
                oldest._drop()
            self._wait_for_head()

        def connection_lost(self, exc: Exception | None) -> None:
            self._stop_waiting()
            super().connection_lost(exc)

        # The request head ----------------------------------------------------------------
        def data_received(self, data: bytes) -> None:
            if self.transport.is_closing():
                return
            if not self._in_head:
                super().data_received(data)
                return
            if self._deadline is None:  # the first byte of a request on a kept-alive connection
                self._wait_for_head()
            search_from = max(len(self._head) - 3, 0)
            self._head += data
            self._head_bytes += len(data)
            if any(self._head.find(end, search_from) >= 0 for end in _HEAD_ENDS):
                head = bytes(self._head)
                self._head.clear()
                super().data_received(head)  # completes the head: on_headers_complete
                return
            if self._head_bytes > limits.max_header_bytes:
                self._refuse(too_large)

        def on_headers_complete(self) -> None:
            self._stop_waiting()
            self._in_head = False
            super().on_headers_complete()

        def on_message_complete(self) -> None:
            super().on_message_complete()
            # What follows is the next request's head (kept-alive or pipelined).
            self._in_head = True
            self._head_bytes = 0
            waiting[self] = None

        # Helpers --------------------------------------------------------------------------
        def _wait_for_head(self) -> None:
            waiting.pop(self, None)
            waiting[self] = None
            if self._deadline is not None:
                self._deadline.cancel()
            self._deadline = self.loop.call_later(limits.header_timeout_s, self._timed_out)

        def _stop_waiting(self) -> None:
            waiting.pop(self, None)
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _timed_out(self) -> None:
            self._deadline = None
            if not self._in_head or self.transport.is_closing():
                return
            if self._head_bytes:
                self._refuse(too_slow)
            else:
                self._drop()

        def _refuse(self, response: bytes) -> None:
            self._stop_waiting()
            self._head.clear()
            self.transport.write(response)
            self.transport.close()

        def _drop(self) -> None:
            self._stop_waiting()
            self._head.clear()
            self.transport.abort()

    return GuardedProtocol
