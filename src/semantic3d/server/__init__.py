"""The self-hostable benchmark server: ``create_app(settings)`` and its settings.

Hidden-label submissions (resumable chunked uploads, validated at once), a crash-safe
database-backed evaluation queue with leases, and public leaderboards. Needs the
``server`` extra (FastAPI, SQLAlchemy, Alembic, …); the submission client in
:mod:`semantic3d.server.client` needs only ``httpx`` and pydantic (it parses the API's
models of :mod:`semantic3d.server.schemas`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from semantic3d.server.app import create_app
    from semantic3d.server.settings import Settings

__all__ = ["Settings", "create_app"]


def __getattr__(name: str) -> Any:
    # Imported lazily so the CLI's ``submit`` (client only) does not load the web stack.
    from semantic3d.core.errors import require

    if name == "create_app":
        require("fastapi", "server")
        from semantic3d.server.app import create_app

        return create_app
    if name == "Settings":
        require("pydantic_settings", "server")
        from semantic3d.server.settings import Settings

        return Settings
    raise AttributeError(f"module 'semantic3d.server' has no attribute {name!r}")
