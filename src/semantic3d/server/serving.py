"""Running the server under uvicorn: the listening socket, the file limit, the HTTP guard.

``semantic3d serve`` (and ``demo --serve``) bind the port *before* anything else runs, so
a busy port is one line and exit code 2 (uvicorn alone prints a traceback-like block and
exits 3, after the app has started); then they raise the soft open-file limit to the
hard one, and run uvicorn on the bound socket with :mod:`.http_guard`'s protocol and the
proxy settings (``X-Forwarded-*`` believed only from ``forwarded_allow_ips``).
"""

from __future__ import annotations

import errno
import logging
import socket
from typing import TYPE_CHECKING, Any

from semantic3d.core.errors import Semantic3DError

if TYPE_CHECKING:
    from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)

_RESERVED_FILES = 256
"""Descriptors kept for the database, uploads being written and the worker's reads."""
_MAX_SOFT_FILES = 1 << 20


class ListenError(Semantic3DError, OSError):
    """The server cannot listen on the address it was given."""


def bind_listener(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` (not listening yet), or :class:`ListenError`.

    The message is one line: ``127.0.0.1:8000: expected a free port to listen on, found
    it in use by another program; pick another with --port``.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        where = f"[{host}]:{port}" if family == socket.AF_INET6 else f"{host}:{port}"
        if exc.errno == errno.EADDRINUSE:
            raise ListenError(
                f"{where}: expected a free port to listen on, found it in use by another "
                "program; pick another with --port"
            ) from None
        if exc.errno == errno.EACCES:
            raise ListenError(
                f"{where}: expected a port this user may listen on, found it reserved "
                "(ports below 1024 need privileges); pick another with --port"
            ) from None
        reason = exc.strerror or str(exc)
        raise ListenError(
            f"{where}: expected an address of this machine to listen on, found "
            f"{reason[:1].lower()}{reason[1:]}; check --host"
        ) from None
    return sock


def check_port_free(host: str, port: int) -> None:
    """Raise :class:`ListenError` now if ``host:port`` could not be listened on."""
    bind_listener(host, port).close()


def raise_open_file_limit() -> int:
    """Raise the soft limit on open files to the hard one (at most 2**20); the new soft.

    Every connection holds a descriptor: with the usual soft limit of 1024, a thousand
    idle clients would leave none for the database or an upload. Where the limit cannot
    be read or changed (not POSIX), returns the current one or 0.
    """
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return 0
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = _MAX_SOFT_FILES if hard == resource.RLIM_INFINITY else min(hard, _MAX_SOFT_FILES)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))
            soft = wanted
        except (ValueError, OSError):
            logger.warning("could not raise the open-file limit from %d to %d", soft, wanted)
    return _MAX_SOFT_FILES if soft == resource.RLIM_INFINITY else int(soft)


def connection_cap(max_connections: int, open_files: int) -> int:
    """``max_connections``, lowered to keep descriptors free under the open-file limit.

    Half of what is left after the reserve: the other half is for connections the kernel
    has queued, which the server accepts in batches before closing those over the cap.

    >>> connection_cap(1000, 1024), connection_cap(1000, 65536), connection_cap(1000, 100)
    (384, 1000, 37)
    """
    if open_files <= 0:
        return max_connections
    return max(1, min(max_connections, _spare_files(open_files) // 2))


def listen_backlog(open_files: int) -> int:
    """Connections the kernel may queue for the server: uvicorn's 2048, or fewer so that
    those and the capped ones fit under the open-file limit with the reserve.

    >>> listen_backlog(1024), listen_backlog(65536)
    (384, 2048)
    """
    if open_files <= 0:
        return 2048
    return max(16, min(2048, _spare_files(open_files) // 2))


def _spare_files(open_files: int) -> int:
    return open_files - min(_RESERVED_FILES, open_files // 4)


def uvicorn_config(
    app: Any, settings: Settings, *, log_level: str = "info", access_log: bool = True
) -> Any:
    """The ``uvicorn.Config`` that serves ``app`` with ``settings``'s limits and proxies.

    Raises the soft open-file limit (:func:`raise_open_file_limit`) to size the
    connection cap.
    """
    from semantic3d.core.errors import require

    require("httptools", "server")
    import uvicorn

    from semantic3d.server.http_guard import ConnectionLimits, guarded_protocol

    open_files = raise_open_file_limit()
    limits = ConnectionLimits(
        max_header_bytes=settings.max_header_bytes,
        header_timeout_s=settings.header_timeout_s,
        max_connections=connection_cap(settings.max_connections, open_files),
    )
    return uvicorn.Config(
        app,
        http=guarded_protocol(limits),
        backlog=listen_backlog(open_files),
        log_level=log_level,
        access_log=access_log,
        proxy_headers=settings.proxy_headers,
        forwarded_allow_ips=settings.forwarded_allow_ips,
        timeout_keep_alive=30,
    )


def run_server(
    app: Any, settings: Settings, sock: socket.socket, *, log_level: str = "info"
) -> None:
    """Serve ``app`` on the bound ``sock`` until interrupted (Ctrl-C, SIGTERM)."""
    import uvicorn

    config = uvicorn_config(app, settings, log_level=log_level)
    uvicorn.Server(config).run(sockets=[sock])
