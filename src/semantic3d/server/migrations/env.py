"""Alembic environment, run programmatically with a connection (``db.run_migrations``)."""

from __future__ import annotations

from alembic import context
from sqlalchemy import text

from semantic3d.server.models import Base

# A fixed key for PostgreSQL's advisory lock: concurrent starters migrate one at a time.
_MIGRATION_LOCK_KEY = 0x53336D69


def _run() -> None:
    connection = context.config.attributes.get("connection")
    if connection is None:
        raise RuntimeError("semantic3d migrations run through semantic3d.server.db.run_migrations")
    context.configure(
        connection=connection,
        target_metadata=Base.metadata,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )
    with context.begin_transaction():
        if connection.dialect.name == "postgresql":
            connection.execute(text(f"SELECT pg_advisory_xact_lock({_MIGRATION_LOCK_KEY})"))
        context.run_migrations()


_run()
