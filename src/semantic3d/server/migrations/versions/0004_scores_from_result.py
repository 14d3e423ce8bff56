"""submissions: scores derived from the stored result; drop the ``n_points`` copy

The point count is part of ``result_json`` (the evaluation result) and no query filters
or sorts on it, so the column that repeated it goes. ``mean_iou``, ``overall_accuracy``
(leaderboard filter and order) and ``iou_json`` (listed by the leaderboard query) stay.
Downgrading restores the column from ``result_json``.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23 18:40:00
"""

from __future__ import annotations

import json

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.drop_column("n_points")


def downgrade() -> None:
    with op.batch_alter_table("submissions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("n_points", sa.BigInteger(), nullable=True))
    submissions = sa.table(
        "submissions",
        sa.column("id", sa.Integer),
        sa.column("n_points", sa.BigInteger),
        sa.column("result_json", sa.Text),
    )
    connection = op.get_bind()
    rows = connection.execute(
        sa.select(submissions.c.id, submissions.c.result_json).where(
            submissions.c.result_json.is_not(None)
        )
    ).all()
    for submission_id, result_json in rows:
        n_points = json.loads(result_json).get("n_points")
        connection.execute(
            sa.update(submissions)
            .where(submissions.c.id == submission_id)
            .values(n_points=n_points)
        )
