"""Errors of the server's library layer; the app maps each to an HTTP status with its message.

``SubmissionError`` and ``DataFormatError`` from :mod:`semantic3d.core.errors` map to 422.
"""

from __future__ import annotations

from semantic3d.core.errors import Semantic3DError


class ServerError(Semantic3DError):
    """Root of the server's errors; ``status_code`` is the HTTP status to answer with."""

    status_code = 400


class InvalidInputError(ServerError, ValueError):
    """A form field or request parameter is malformed (400)."""

    status_code = 400


class AuthenticationError(ServerError, PermissionError):
    """Missing or wrong credentials (401)."""

    status_code = 401


class ForbiddenError(ServerError, PermissionError):
    """Authenticated, but not allowed (403); also a missing or wrong CSRF token."""

    status_code = 403


class NotFoundError(ServerError, LookupError):
    """No such resource, or one the caller may not see (404)."""

    status_code = 404


class ConflictError(ServerError, ValueError):
    """The request contradicts the resource's state, e.g. a chunk at the wrong offset (409)."""

    status_code = 409

    def __init__(self, message: str, *, offset: int | None = None) -> None:
        super().__init__(message)
        self.offset = offset


class TooLargeError(ServerError, ValueError):
    """An upload exceeds the configured byte cap (413)."""

    status_code = 413


class UploadIncompleteError(ServerError, ValueError):
    """Finalising an upload that has not received all its bytes (409, resumable)."""

    status_code = 409


class ThrottledError(ServerError, PermissionError):
    """Too many attempts or a submission quota reached (429); ``retry_after_s`` says when."""

    status_code = 429

    def __init__(self, message: str, *, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class RequestTimeoutError(ServerError):
    """A request body stopped arriving for longer than the read timeout (408)."""

    status_code = 408


class ServiceUnavailableError(ServerError, RuntimeError):
    """The server is too busy now (503); ``retry_after_s`` says when to try again."""

    status_code = 503

    def __init__(self, message: str, *, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class InsufficientStorageError(ServerError):
    """The server's disk has too little free space for the request (507)."""

    status_code = 507
