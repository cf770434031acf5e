"""Ingest hardening: repeated deliveries and the ingest's owner on downlinks, and the files of a
downlink that are not used, with why.

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-02

The downlink columns are additions (repeat_count with a server default for the rows there), so
SQLite adds and drops them in place without rebuilding the downlinks table, which other tables
reference.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

UTC_TIME = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.add_column("downlinks", sa.Column("repeat_count", sa.Integer(), server_default="0",
                                         nullable=False))
    op.add_column("downlinks", sa.Column("last_seen_at", UTC_TIME, nullable=True))
    op.add_column("downlinks", sa.Column("ingest_owner", sa.String(length=255), nullable=True))
    op.add_column("downlinks", sa.Column("ingest_heartbeat_at", UTC_TIME, nullable=True))
    op.create_table(
        "downlink_files",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("downlink_id", sa.Integer(), nullable=False),
        sa.Column("path", sa.Text(), nullable=False),
        sa.Column("code", sa.String(length=32), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("seen_at", UTC_TIME, nullable=False),
        sa.ForeignKeyConstraint(["downlink_id"], ["downlinks.id"], ondelete="CASCADE",
                                name=op.f("fk_downlink_files_downlink_id")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_downlink_files")),
        sa.UniqueConstraint("downlink_id", "path", name=op.f("uq_downlink_files_downlink_id_path")),
    )


def downgrade() -> None:
    op.drop_table("downlink_files")
    for column in ("ingest_heartbeat_at", "ingest_owner", "last_seen_at", "repeat_count"):
        op.drop_column("downlinks", column)
