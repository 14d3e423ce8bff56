"""challenges: listed before their ground truth is installed; confusion-matrix policy

``semantic-8`` and ``reduced-8`` are recorded from the start (closed, ground truth not
installed) so a fresh server lists them with the paper's reference results; installing
their ground truth (``semantic3d admin add-challenge``) completes the row and opens it.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23 17:40:00
"""

from __future__ import annotations

from datetime import UTC, datetime

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

_DESCRIPTIONS = {
    "semantic-8": "semantic3D.net, full test set",
    "reduced-8": "semantic3D.net, reduced test set",
}


def upgrade() -> None:
    with op.batch_alter_table("challenges", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column(
                "ground_truth_installed", sa.Boolean(), nullable=False, server_default=sa.true()
            )
        )
        batch_op.add_column(sa.Column("show_confusion", sa.Boolean(), nullable=True))
    _list_benchmark_challenges()


def _list_benchmark_challenges() -> None:
    """Insert ``semantic-8``/``reduced-8`` (closed, no ground truth) unless already installed."""
    from semantic3d.evaluation import load_challenge

    challenges = sa.table(
        "challenges",
        sa.column("name", sa.String),
        sa.column("kind", sa.String),
        sa.column("title", sa.String),
        sa.column("description", sa.Text),
        sa.column("protocol_version", sa.String),
        sa.column("n_scans", sa.Integer),
        sa.column("n_points", sa.BigInteger),
        sa.column("scan_points_json", sa.Text),
        sa.column("is_open", sa.Boolean),
        sa.column("created_at", sa.DateTime),
        sa.column("ground_truth_installed", sa.Boolean),
    )
    connection = op.get_bind()
    present = set(connection.execute(sa.select(challenges.c.name)).scalars())
    now = datetime.now(UTC).replace(tzinfo=None)
    rows = []
    for name, description in _DESCRIPTIONS.items():
        if name in present:
            continue
        built = load_challenge(name, ground_truth_root=None)
        counts = [scan.n_points for scan in built.scans]
        rows.append(
            {
                "name": name,
                "kind": name,
                "title": name,
                "description": description,
                "protocol_version": str(built.protocol_version),
                "n_scans": len(built.scans),
                "n_points": sum(c for c in counts if c is not None)
                if all(c is not None for c in counts)
                else None,
                "scan_points_json": "{}",
                "is_open": False,
                "created_at": now,
                "ground_truth_installed": False,
            }
        )
    if rows:
        op.bulk_insert(challenges, rows)


def downgrade() -> None:
    connection = op.get_bind()
    connection.execute(sa.text("DELETE FROM challenges WHERE NOT ground_truth_installed"))
    with op.batch_alter_table("challenges", schema=None) as batch_op:
        batch_op.drop_column("show_confusion")
        batch_op.drop_column("ground_truth_installed")
