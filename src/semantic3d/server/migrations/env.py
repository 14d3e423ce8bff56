"""Alembic environment, run programmatically with a connection (``db.run_migrations``)."""

from __future__ import annotations

from alembic import context
from sqlalchemy import text

from semantic3d.server.db import MIGRATION_LOCK_KEY
from semantic3d.server.models import Base


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
            # a migration waits for the one before it and for running transactions, however
            # long: the requests' lock bound does not apply here
            connection.execute(text("SET LOCAL lock_timeout = 0"))
            connection.execute(text(f"SELECT pg_advisory_xact_lock({MIGRATION_LOCK_KEY})"))
        context.run_migrations()


_run()
